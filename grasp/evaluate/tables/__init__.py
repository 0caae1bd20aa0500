"""The evaluation's tables, each one module: which jobs it needs, how it scores one, what it puts
in results.json and how it writes its part of results.md (:class:`~grasp.evaluate.tables.base.
Table`). Adding a table: a module with a Table and one line in :data:`TABLES` (whose order is the
order of the jobs, and of results.md within a section of the main table's report); a table with a
size of its own declares it (:class:`~grasp.evaluate.tables.base.Sizing`: its ``--<name>``
option and its size per preset), and the command line and the run's settings take it from there."""

from grasp.evaluate.tables import benchmark, clutter, main, objects, overhead, sensor
from grasp.evaluate.tables.base import Sizing, Table

TABLES: tuple[Table, ...] = (
    main.MAIN,  # the paper's Tables I–III, their precision, grasp success
    sensor.TABLE,  # each condition with and without the sensor model, paired
    overhead.TABLE,  # tabletop seen from above: the share of the completion below the table
    benchmark.TABLE,  # the grasp-success benchmark: objects on a table, lift-tested
    clutter.TABLE,  # a target among neighbours: the neighbours as obstacles, and not
    objects.NAMED,  # the held-out named pybullet_data objects
    objects.FOLDER,  # every mesh of --objects DIR
)
BY_NAME: dict[str, Table] = {table.name: table for table in TABLES}

__all__ = ["BY_NAME", "TABLES", "Sizing", "Table"]
