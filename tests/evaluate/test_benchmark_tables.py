"""The benchmark tables never put numbers of two Chamfer protocols in one column or mean."""

from __future__ import annotations

import csv
import io

import pytest

from svolsdf.errors import InputError
from svolsdf.evaluate.benchmark_tables import (
    _table,
    benchmark_csv,
    benchmark_markdown,
    benchmark_plot,
    protocol_groups,
)


def _row(scene, mode, acc, comp, protocol):
    return {"scene": scene, "mode": mode, "accuracy": acc, "completeness": comp,
            "overall": None if acc is None else (acc + comp) / 2, "time_s": 5.0,
            "status": "ok" if acc is not None else "failed: boom", "protocol": protocol}


ROWS = [_row("scan24", "svolsdf", 1.0, 2.0, "dtu"), _row("syn", "svolsdf", 13.0, 15.0, "generic"),
        _row("scan37", "svolsdf", 2.0, 2.0, "dtu"), _row("syn", "mvs-only", None, None, None)]


def test_rows_of_two_protocols_never_share_a_column_or_a_mean(tmp_path):
    with pytest.raises(InputError, match="different Chamfer protocols.*dtu: scan24 / svolsdf"):
        _table(ROWS, None)
    assert [(p, [r["scene"] for r in g]) for p, g in protocol_groups(ROWS)] == [
        ("dtu", ["scan24", "scan37"]), ("generic", ["syn", "syn"])]
    md = benchmark_markdown(ROWS, title="T")
    assert md.count("| **mean** |") == 2 and "one table per protocol" in md
    dtu = md[md.index("## Chamfer protocol: dtu (DTU protocol"):md.index("## Chamfer protocol: "
                                                                           "generic")]
    assert "| **mean** | 1.50 | 2.00 | 1.75 |" in dtu and "syn" not in dtu
    generic = md[md.index("## Chamfer protocol: generic (generic two-way Chamfer"):]
    assert "| syn | 13.00 | 15.00 | 14.00 |" in generic and "- syn / mvs-only: failed" in generic
    table = list(csv.reader(io.StringIO(benchmark_csv(ROWS))))
    assert table[0][:2] == ["protocol", "scene"]
    assert [r[:2] for r in table[1:]] == [["dtu", "scan24"], ["dtu", "scan37"], ["dtu", "mean"],
                                          ["generic", "syn"], ["generic", "mean"]]
    benchmark_plot(ROWS, tmp_path / "b.png")
    assert (tmp_path / "b_dtu.png").is_file() and (tmp_path / "b_generic.png").is_file()
    # one protocol: the table as before, one mean
    one = benchmark_markdown(ROWS[:1] + ROWS[2:3])
    assert one.count("| **mean** |") == 1 and "## Chamfer protocol" not in one
