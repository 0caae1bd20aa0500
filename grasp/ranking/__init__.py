"""The ranking of autograsped grasps: the sort key, distinct grasps, the lift model's hold
probability on a table, and the one function that ranks, keeps distinct grasps and verifies them
in physics (:func:`grasp.ranking.rank.select`), shared by the CLI, the service and the
evaluation."""
