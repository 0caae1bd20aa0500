"""The object tables: the held-out named pybullet_data objects, and every mesh of ``--objects
DIR``; camera pan, test split, one sequence per object, every metric of the main table."""

from __future__ import annotations

from completion.objects import object_ids
from grasp.evaluate.aggregate import aggregate
from grasp.evaluate.cells import CEILING_LABEL, fmt
from grasp.evaluate.config import (
    FSCORE_METRICS,
    METRICS,
    ROW_LABELS,
    Job,
    Settings,
)
from grasp.evaluate.sequence_result import SequenceResult
from grasp.evaluate.tables.base import Option, Table

#: The condition of the named-object and ``--objects`` tables.
OBJECT_TABLE_CONDITION = "camera_pan"
NAMED_OBJECTS_TABLE, FOLDER_TABLE = "named", "objects"
#: ``--named N``: the named objects evaluated.
NAMED_SIZE = Option(NAMED_OBJECTS_TABLE, "held-out named pybullet_data objects to evaluate",
                    quick=3, default=5, full=10)


class ObjectTable(Table):
    section = "objects"

    def __init__(self, name: str, key: str, title: str, options: tuple[Option, ...] = ()) -> None:
        self.name, self.key, self.title = name, key, title  # key: its results.json entry
        self.options = options

    def objects(self, settings: Settings) -> list[str]:
        if self.name == NAMED_OBJECTS_TABLE:
            return object_ids("test", sources=("named",))[: NAMED_SIZE.of(settings)]
        return list(settings.objects)

    def jobs(self, settings: Settings) -> list[Job]:
        return [Job(self.name, OBJECT_TABLE_CONDITION, "test", index, pool=(object_id,),
                    grasp=settings.grasp_count > 0, example=index == 0)
                for index, object_id in enumerate(self.objects(settings))]

    def summarise(self, results: list[SequenceResult], settings: Settings) -> dict:
        """Its objects' cells per row and metric, counts, grasp failures and F-score ceiling."""
        if not any(r.job.table == self.name for r in results):
            return {self.key: None}
        agg = aggregate(results, settings, self.name)
        c = OBJECT_TABLE_CONDITION
        return {self.key: {
            "condition": c,
            "split": "test",
            "tables": {m: {row: agg["tables"][m][row][c]["test"] for row in settings.rows}
                       for m in METRICS},
            "counts": {row: agg["counts"][row][c]["test"] for row in settings.rows},
            "grasp_failures": {row: agg["grasp_failures"][row][c]["test"]
                               for row in settings.rows},
            "fscore_ceiling": agg["ceiling"][c]["test"],
            "objects": [r.object_ids[0] for r in results if r.job.table == self.name],
        }}

    def markdown(self, results: dict) -> list[str]:
        block = results.get(self.key)
        if not block:
            return []
        return [f"## {self.title} (camera pan, test)", "",
                f"Objects: {', '.join(block['objects'])}", "", markdown_object_table(block), ""]


def markdown_object_table(block: dict) -> str:
    """Rows = models, columns = the metrics (camera_pan, test objects only)."""
    tables = block["tables"]
    rows = list(tables["jaccard"])
    lines = [
        "| Model | Jaccard | F@1% | F@2% | Joint error (8) | Joint error (6 moving) | grasps ok |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        n = block["counts"][row]
        cells = [fmt(tables[m][row], m) for m in METRICS]
        lines.append(
            f"| {ROW_LABELS[row]} | " + " | ".join(cells) + f" | {n['grasp_ok']}/{n['grasped']} |"
        )
    ceiling = block.get("fscore_ceiling")
    if ceiling:
        f1, f2 = (fmt(ceiling[m], m) for m in FSCORE_METRICS)
        lines.append(f"| {CEILING_LABEL} | 1.00 | {f1} | {f2} | — | — | |")
    notes = [
        f"- {ROW_LABELS[row]}: {'; '.join(reasons)}"
        for row, reasons in block["grasp_failures"].items()
        if reasons
    ]
    if notes:
        lines += ["", "Grasps without a comparable result:", "", *notes]
    return "\n".join(lines)


NAMED = ObjectTable(NAMED_OBJECTS_TABLE, "named_objects", "Held-out named pybullet_data objects",
                    (NAMED_SIZE,))
FOLDER = ObjectTable(FOLDER_TABLE, "objects_dir", "Objects from --objects")
