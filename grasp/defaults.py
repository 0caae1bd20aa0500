"""The planner's defaults that other parts name (the service's settings, the evaluation), in a
module that imports nothing, so that naming them does not load the planner's stack."""

#: Candidates the planner autograsps exactly, the screen's most promising first (the search's
#: budget; docs/grasping.md says how it was chosen). A count, not a time: the grasp does not
#: depend on the machine's load.
AUTOGRASP_BUDGET = 16
#: On a table, a force-closure grasp the lift model gives less than this chance to hold is a
#: failure that says so (:mod:`grasp.ranking.lift_model`; on the benchmark's true meshes every top
#: grasp below it dropped), unless the caller asks for less (``min_hold``: a robot that will
#: decide itself, or try it in physics first).
HOLD_THRESHOLD = 0.5
