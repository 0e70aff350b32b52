"""`svolsdf.io.replace` on a toy command: what is refused before any work, what a failure leaves,
and what a write killed while swapping leaves for the next run."""

from __future__ import annotations

import json
import os
import re

import pytest

from svolsdf.errors import InputError
from svolsdf.io.replace import RECORD_NAME, OutputSpec, check_replace, replace_outputs


def _legacy(out):
    return ({"data/a.txt": None, "summary.json": None} if (out / "summary.json").is_file()
            else None)


SPEC = OutputSpec(command="svolsdf toy", names=frozenset({"data", "summary.json"}),
                  keeps=frozenset({"logs"}), earlier="a toy output", legacy=_legacy)


def _write(out, files=("a.txt", "b.txt")):
    with replace_outputs(out, SPEC) as stage:
        (stage / "data").mkdir()
        for n in files:
            (stage / "data" / n).write_text(n)
        (stage / "summary.json").write_text("{}")


def test_a_rerun_replaces_its_own_files_and_keeps_the_users(tmp_path):
    out = tmp_path / "out"
    _write(out)
    (out / "notes.txt").write_text("mine")
    _write(out, files=("c.txt",))
    assert sorted(p.name for p in (out / "data").iterdir()) == ["c.txt"]
    assert (out / "notes.txt").read_text() == "mine"
    rec = json.loads((out / RECORD_NAME).read_text())
    assert rec == {"command": "svolsdf toy", "files": {"data/c.txt": 5, "summary.json": 2}}
    assert sorted(p.name for p in out.iterdir()) == [RECORD_NAME, ".svolsdf.lock", "data",
                                                     "notes.txt", "summary.json"]


def test_a_failure_leaves_the_folder_as_it_was(tmp_path):
    out = tmp_path / "out"
    _write(out)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(KeyboardInterrupt), replace_outputs(out, SPEC) as stage:
        (stage / "data").mkdir()
        raise KeyboardInterrupt
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    # a new folder that stayed empty is removed again; one the command added to stays
    new = tmp_path / "new"
    with pytest.raises(InputError), replace_outputs(new, SPEC):
        raise InputError("bad input")
    assert not new.exists()
    with pytest.raises(InputError), replace_outputs(new, SPEC):
        (new / "logs").mkdir()
        raise InputError("too few photos")
    assert sorted(p.name for p in new.iterdir()) == [".svolsdf.lock", "logs"]


@pytest.mark.parametrize("change", ["added", "changed", "link", "foreign folder",
                                    "other command", "input inside"])
def test_refused_before_any_work(tmp_path, change):
    out = tmp_path / "out"
    _write(out)
    inputs = []
    if change == "added":
        (out / "data" / "mine.txt").write_text("mine")
    elif change == "changed":
        (out / "data" / "a.txt").write_text("edited by the user")
    elif change == "link":
        (out / "data" / "a.txt").unlink()
        (out / "data" / "a.txt").symlink_to(tmp_path / "elsewhere")
    elif change == "foreign folder":
        out = tmp_path / "photos"
        out.mkdir()
        (out / "1.jpg").write_text("a photo")
    elif change == "other command":
        (out / RECORD_NAME).write_text(json.dumps({"command": "svolsdf other", "files": {}}))
    elif change == "input inside":
        inputs = [out / "data"]
    before = sorted(os.walk(out))
    with pytest.raises(InputError, match=f"^-o {out}: ") as e:
        check_replace(out, SPEC, inputs)
    with pytest.raises(InputError, match=re.escape(str(e.value))):
        with replace_outputs(out, SPEC, inputs):
            raise AssertionError("no work starts")
    assert sorted(os.walk(out)) == before


def test_inputs_and_logs_beside_the_output_are_kept(tmp_path):
    out = tmp_path / "scene"
    (out / "photos").mkdir(parents=True)
    (out / "photos" / "1.jpg").write_text("a photo")
    (out / "logs").mkdir()
    _write_with_input = replace_outputs(out, SPEC, [out / "photos"])
    with _write_with_input as stage:
        (stage / "summary.json").write_text("{}")
    assert (out / "photos" / "1.jpg").read_text() == "a photo" and (out / "logs").is_dir()


def test_an_output_written_before_the_record_is_read_through_its_summary(tmp_path):
    out = tmp_path / "out"
    (out / "data").mkdir(parents=True)
    (out / "data" / "a.txt").write_text("old")
    (out / "summary.json").write_text("{}")
    (out / "data" / "mine.txt").write_text("mine")
    with pytest.raises(InputError, match="mine.txt is not a file svolsdf toy wrote"):
        check_replace(out, SPEC)
    (out / "data" / "mine.txt").unlink()
    _write(out)
    assert (out / "data" / "b.txt").is_file()


def test_a_write_killed_while_swapping_is_taken_up_by_the_next(tmp_path):
    """The record lists both outputs while they are swapped: a rerun after a kill there finds
    only recorded files, and removes what the killed write left aside."""
    out = tmp_path / "out"
    _write(out)
    rec = json.loads((out / RECORD_NAME).read_text())
    # killed after moving the earlier data/ aside and the new one in, before the last record
    aside = out / ".svolsdf-replaced.1.00000000"
    aside.mkdir()
    os.replace(out / "data", aside / "data")
    (out / "data").mkdir()
    (out / "data" / "z.txt").write_text("z")
    rec["files"]["data/z.txt"] = 1  # the record of both
    (out / RECORD_NAME).write_text(json.dumps(rec))
    (out / ".svolsdf-staging.1.00000000").mkdir()
    check_replace(out, SPEC)
    _write(out, files=("c.txt",))
    assert sorted(p.name for p in out.iterdir()) == [RECORD_NAME, ".svolsdf.lock", "data",
                                                     "summary.json"]
