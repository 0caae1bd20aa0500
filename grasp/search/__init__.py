"""The search: candidate pre-grasps around an object, the distance-field screen that orders them,
the obstacles beside it, and the budgeted autograsp loop over the screen's most promising
candidates (:mod:`grasp.search.loop`). Uses :mod:`grasp.hand`; knows nothing of the ranking."""
