"""The evaluation's tables, each one module: its command-line options, which jobs it needs, how it
scores one, what it puts in results.json and how it writes its part of results.md
(:class:`~grasp.evaluate.tables.base.Table`). Adding a table: a module with a Table and one line in
:data:`TABLES` (whose order is the order of the jobs, of the options in ``--help``, and of
results.md within a section of the main table's report); a table with options of its own declares
them (:class:`~grasp.evaluate.tables.base.Option`: ``--<name>`` and its value per preset), and the
command line and the run's settings take them from there."""

from grasp.evaluate.config import Settings
from grasp.evaluate.tables import benchmark, clutter, main, objects, overhead, sensor
from grasp.evaluate.tables.base import Option, Table

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
#: Every table's options, by name.
OPTIONS: dict[str, Option] = {o.name: o for table in TABLES for o in table.options}
if len(OPTIONS) != sum(len(t.options) for t in TABLES):
    raise RuntimeError("two tables declare an option of one name")


def check_options(settings: Settings) -> None:
    """Raise ValueError for an option of ``settings`` that no table has, one named twice, or one
    below its least."""
    names = [name for name, _ in settings.options]
    if len(set(names)) != len(names):
        raise ValueError(f"an option named twice: {names}")
    for name, value in settings.options:
        if name not in OPTIONS:
            raise ValueError(f"no table has an option {name!r}; the options: {list(OPTIONS)}")
        if value < OPTIONS[name].least:
            raise ValueError(f"{name} out of range: {value} (at least {OPTIONS[name].least})")


__all__ = ["BY_NAME", "OPTIONS", "TABLES", "Option", "Table", "check_options"]
