"""The planner's defaults that other parts name (the service's settings, the evaluation), in a
module that imports nothing, so that naming them does not load the planner's stack."""

#: Candidates the planner autograsps exactly, the screen's most promising first (the search's
#: budget; docs/grasping.md says how it was chosen). A count, not a time: the grasp does not
#: depend on the machine's load.
AUTOGRASP_BUDGET = 16
