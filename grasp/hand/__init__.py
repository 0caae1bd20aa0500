"""The GraspIt!-style hand on a mesh: the collision scene, the autograsp (approach until contact,
close until contact, the Barrett breakaway), the table pinch, the table as an obstacle, and the
grasp's quality. Kinematic and deterministic; nothing here knows about candidates, rankings or
physics (docs/design.md §2)."""
