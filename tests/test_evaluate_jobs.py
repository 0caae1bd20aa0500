"""How the evaluation plans its sequences (grasp/evaluate/runner.py make_jobs): the sensor table
pairs every condition with and without the sensor, and grasps beyond --count are grasp-only."""

from completion.scenes import CONDITIONS, SINGLE_OBJECT_CONDITIONS
from grasp import evaluate as ev
from grasp.evaluate.tables.sensor import SENSOR_TABLE


def test_sensor_jobs_pair_every_condition_and_extra_grasps_are_grasp_only():
    jobs = ev.make_jobs(ev.Settings(rows=(ev.FUSION,), count=1, grasp_count=3, physics_count=2,
                                    options=(("sensor", 2), ("named", 0), ("benchmark", 0),
                                             ("overhead", 0), ("clutter", 0))))
    sensor = {(j.condition, j.index, j.noise) for j in jobs if j.table == SENSOR_TABLE}
    for c in CONDITIONS:  # the main table holds index 0 on the condition's default side
        d = c == "tabletop"
        assert {(c, 0, not d), (c, 1, True), (c, 1, False)} <= sensor and (c, 0, d) not in sensor
    extra = [j for j in jobs if j.grasp_only]
    assert {(j.condition, j.split, j.index) for j in extra} == {
        (c, "test", i) for c in SINGLE_OBJECT_CONDITIONS for i in (1, 2)}
    assert all(j.grasp and j.table == ev.MAIN_TABLE for j in extra)
    assert [j.physics for j in extra if j.condition == "camera_pan"] == [True, False]
    assert sum(j.table == ev.MAIN_TABLE and j.split == "train" for j in jobs) == len(CONDITIONS)
