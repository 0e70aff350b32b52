"""`svolsdf.io.paths`: ``~`` expanded, and one message per cause naming the path."""

from __future__ import annotations

import errno
import os
import tempfile

import pytest

from svolsdf.errors import InputError
from svolsdf.io.paths import (
    input_dir,
    input_file,
    input_path,
    output_dir,
    output_file,
    path_label,
    user_path,
)


@pytest.fixture
def here(tmp_path, monkeypatch):
    """A working folder with a space and a non-ASCII letter in its name, also HOME."""
    d = tmp_path / "dé mo"
    d.mkdir()
    monkeypatch.chdir(d)
    monkeypatch.setenv("HOME", str(d))
    return d


def _refusal(fn, *args, **kw) -> str:
    with pytest.raises(InputError) as e:
        fn(*args, **kw)
    return str(e.value)


def test_user_path_expands_only_the_tilde(here):
    assert user_path("~/a b/ü") == here / "a b" / "ü"
    assert str(user_path("x/../y")) == "x/../y"  # kept: the OS resolves it
    assert path_label("a b", "--scenes") == f"--scenes a b ({here}/a b)"
    assert path_label(str(here / "a")) == str(here / "a")


def test_inputs_that_exist_are_returned_expanded(here):
    (here / "my scans" / "scan 1").mkdir(parents=True)
    (here / "c.yaml").write_text("x")
    assert input_dir("~/my scans/scan 1") == here / "my scans" / "scan 1"
    assert input_dir("my scans/../my scans/scan 1") == user_path("my scans/../my scans/scan 1")
    assert input_file("~/c.yaml") == here / "c.yaml"
    assert input_path("my scans") == user_path("my scans")
    (here / "link").symlink_to(here / "my scans")
    assert input_dir("link/scan 1").is_dir()


def test_each_cause_of_an_input_is_named(here):
    (here / "afile").write_text("x")
    (here / "adir").mkdir()
    (here / "dangling").symlink_to(here / "gone" / "t")
    (here / "loop").symlink_to(here / "loop")
    assert _refusal(input_dir, "adir/x", "scene folder") == (
        f"adir/x ({here}/adir/x): scene folder does not exist")
    assert _refusal(input_dir, "/no such/scan 1", "scene folder", "--scenes") == (
        "--scenes /no such/scan 1: scene folder does not exist: /no such does not exist")
    assert _refusal(input_dir, "afile", "scene folder") == (
        f"afile ({here}/afile): scene folder is a file, not a folder")
    assert _refusal(input_dir, "afile/x", "scene folder").endswith(
        "scene folder does not exist: afile is a file, not a folder")
    assert _refusal(input_file, "adir", "config file", "--config") == (
        f"--config adir ({here}/adir): config file is a folder, not a file")
    assert _refusal(input_dir, "dangling", "scene folder") == (
        f"dangling ({here}/dangling): scene folder is a symbolic link to {here}/gone/t, which "
        "does not exist")
    assert _refusal(input_file, "dangling/c.yaml", "config file").endswith(
        f"config file does not exist: dangling is a symbolic link to {here}/gone/t, which does "
        "not exist")
    assert "loop" in _refusal(input_dir, "loop", "scene folder")
    assert _refusal(input_dir, "~/nope", "run folder") == (
        f"~/nope ({here}/nope): run folder does not exist")
    assert "empty path" in _refusal(input_dir, "", "scene folder", "-o")


def test_a_relative_link_target_is_shown_as_stored_and_absolute(here):
    (here / "rel").symlink_to("gone/t")
    assert _refusal(input_dir, "rel", "folder").endswith(
        f"is a symbolic link to gone/t ({here}/gone/t), which does not exist")


def test_output_folders_are_made_or_refused_naming_the_cause(here):
    assert output_dir("a b/c", create=False) == user_path("a b/c")
    assert not (here / "a b").exists()  # checked, not made
    assert output_dir("~/a b/c").is_dir()
    (here / "afile").write_text("x")
    assert _refusal(output_dir, "afile", "output folder", "-o") == (
        f"-o afile ({here}/afile): output folder is a file, not a folder; give a folder")
    assert _refusal(output_dir, "afile/x") == (
        f"afile/x ({here}/afile/x): cannot make the output folder: afile is a file, not a "
        "folder")


def test_an_output_link_to_a_new_folder_is_made_through_the_link(here):
    (here / "runs").mkdir()
    (here / "out").symlink_to(here / "runs" / "r 1")
    assert output_dir("out", create=False) == user_path("out")
    assert not (here / "runs" / "r 1").exists()
    output_dir("out")
    assert (here / "out").is_symlink() and (here / "runs" / "r 1").is_dir()
    # its target's folder missing too: refused, naming link, target and the missing folder
    (here / "far").symlink_to(here / "disk" / "r")
    assert _refusal(output_dir, "far", "output folder", "-o") == (
        f"-o far ({here}/far): output folder is a symbolic link to {here}/disk/r, which does "
        f"not exist, and it cannot be made there: {here}/disk does not exist; create that "
        "folder or point the link elsewhere")
    assert not (here / "disk").exists()


def test_unwritable_output_folders_are_named(here, monkeypatch):
    def read_only(*a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    (here / "ro").mkdir()
    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    assert _refusal(output_dir, "ro", "run folder") == (
        f"ro ({here}/ro): cannot write the run folder (Read-only file system); choose a "
        "writable folder")
    assert _refusal(output_dir, "ro/new", "output folder") == (
        f"ro/new ({here}/ro/new): cannot write the output folder: ro is not writable "
        "(Read-only file system); choose a writable folder")
    assert not (here / "ro" / "new").exists()


def test_output_files(here):
    assert output_file("a b/sheet.png", create=False) == user_path("a b/sheet.png")
    assert not (here / "a b").exists()
    assert output_file("a b/sheet.png") and (here / "a b").is_dir()
    assert _refusal(output_file, "a b", "contact sheet", "--sheet") == (
        f"--sheet a b ({here}/a b): contact sheet is a folder, not a file; give a file name")
    (here / "s.png").symlink_to(here / "disk" / "s.png")
    assert _refusal(output_file, "s.png", "contact sheet").endswith(
        f"contact sheet is a symbolic link to {here}/disk/s.png, which cannot be written: "
        f"{here}/disk does not exist; point the link elsewhere")
