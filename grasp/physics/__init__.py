"""Physics check of a grasp: close the BarrettHand on the true object in pybullet, lift, shake.

:func:`lift_test` replays a planned :class:`grasp.hand.autograsp.GraspResult` in rigid-body dynamics
and says whether the object stays in the hand. One trial, in its own DIRECT pybullet client
(:class:`DynamicWorld`; no module-global client):

1. **Object**: the mesh as a dynamic body. Mass and inertia at ``density`` (default
   :data:`DENSITY_KG_M3` = 500 kg/m³, solid), from the mesh when it is a closed volume, otherwise
   from its convex pieces. Collision: the convex hull when the mesh is convex, else pybullet's
   V-HACD decomposition (:func:`convex_decomposition`), cached per mesh in
   ``~/.cache/mvp-grasp/convex``. pybullet pads a hull by its 1 mm margin, so the pieces are
   shrunk by as much and the collision surface is the mesh's (a test checks it against the
   planner's contact). Without a table (the scenes float the object) a weak support, a constraint
   of at most the object's weight, keeps it from drifting while gravity is off and the hand closes;
   with a ``support_plane`` it stands on that table (simulated in the plane's upright frame) with
   gravity on throughout.
2. **Hand**: the URDF from :mod:`hands.barrett.urdf` (implicit cylinders, so the palm is not padded
   either), free base, carried by a fixed constraint to the world whose target is moved every step
   (``changeConstraint``, at most ``hand_force``): the hand base is driven dynamically, so contacts
   see its real velocity. The carriage only translates; the palm keeps the grasp's orientation.
   Finger–finger and finger–palm collisions are off, as in autograsp.
   It starts open, at the grasp's spread, ``pregrasp_backoff`` behind the palm pose along the
   approach axis (:func:`grasp.hand.autograsp.pregrasp_pose`) and moves to the planned pose, or,
   with ``approach="guarded"`` (how a robot executes a plan, and the benchmark's), toward it until
   it first touches the object or the table, on past it for a plan whose approach ended touching.
3. **Close**: every finger DOF rises at ``close_speed``; J2 = DOF and J3 = DOF/3 under position
   control with torque limits. The controller (:meth:`grasp.physics.fingers.FingerController.drive`)
   watches each proximal joint's lag and velocity: stalled while its distal still moves is a
   proximal contact, so the finger breaks away (J2 keeps pressing with its torque limit, the distal
   target keeps following DOF/3 until it stalls or the DOF tops out); stalled together with the
   distal stops the finger (both joints press with their limits). Closing ends when every finger has
   stopped, plus ``close_settle``.
4. **Load**: where the object sits in the palm frame is the reference. The support goes, gravity
   comes on; settle, lift the hand by ``lift`` along world +z (cosine profile), hold, then
   ``shake_count`` shakes along seeded random directions (out and back, one cycle each), hold.

Success: the object's centre of mass never moves more than ``hold_tolerance`` (2 cm) from the
reference, in the palm frame, from gravity-on to the end. The simulation stops early once the
object is ``drop_distance`` (5 cm) away.

Numbers (:class:`LiftSettings`, in one place; the hand's facts: ``hands/barrett/README.md``):

- Time step 1/240 s, 100 solver iterations, deterministic overlapping pairs, friction anchors (they
  stop the slow creep of a held object that pybullet shows without them). The same inputs and
  seed give bit-identical results on one machine.
- Torque limits: J3 1.0 N·m, from the BH8-series manual's "2 kg at the fingertip is about 20 N at
  5 cm = 1 N·m" (the range of its distal torque sensor); the hand motor's 0.0367 N·m continuous
  torque through the 93.75:1 distal drive and a worm of about 30 % efficiency gives the same. J2
  4/3 N·m: the same motor through 125:1 instead of 93.75:1. Spread 2.0 N·m (chosen; the
  worm-driven spread does not back-drive). Finger DOF speed 1 rad/s (the real hand closes its 140°
  in about 1 s; slower keeps the first touch from batting the object away). After a finger stops,
  its joints keep pressing with their limits (standing in for the non-back-drivable worm drives
  holding the squeeze).
- Friction: hand links get ``friction`` (default μ = 1.0, rubber,
:data:`grasp.hand.quality.MU_RUBBER`)
  and the object 1.0; pybullet multiplies the two, so a hand–object contact has exactly μ. No
  rolling or spinning friction.
- Shake: 4 cycles of 3 cm at 3 Hz, peak acceleration 2π²f²A ≈ 5.3 m/s² (about 0.5 g).
- Sim time: 0.5 s approach, up to 3.5 s closing, 3.1 s loaded (settle 0.25, lift 1.0, hold 0.25,
  shakes 1.33, hold 0.25); about 1–2 s of wall time on one core.

Modules: ``settings`` (every number, :class:`LiftSettings`), ``body`` (convex pieces, mass),
``hand`` (the URDF loader both pybullet worlds use), ``fingers`` (the Barrett closing controller),
``world`` (:class:`DynamicWorld`), ``lift`` (:func:`lift_test`), ``verify`` (grasps tried before a
plan answers). This package imports no planner and, like its modules, not torch
(docs/design.md §2); it re-exports nothing, so that ``grasp.physics.verify`` loads no pybullet.
"""
