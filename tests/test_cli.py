"""experiments.cli: the output checks and the atomic JSON writer every CLI shares."""
from __future__ import annotations

import argparse
import json
import os

import pytest

from experiments import cli


def _parser():
    return argparse.ArgumentParser(prog="x")


def test_write_json_writes_and_leaves_no_temporary_file(tmp_path, capsys):
    path = tmp_path / "sub" / "r.json"
    cli.write_json(str(path), {"a": [1, 2]})
    assert json.loads(path.read_text()) == {"a": [1, 2]}
    assert os.listdir(path.parent) == ["r.json"]
    assert capsys.readouterr().out.strip() == f"wrote {path}"


def test_write_json_failure_keeps_the_old_file(tmp_path):
    path = tmp_path / "r.json"
    path.write_text('{"old": 1}')
    with pytest.raises(TypeError):  # not serialisable: fails mid-write (a bug, not a user error)
        cli.write_json(str(path), {"bad": object()})
    assert json.loads(path.read_text()) == {"old": 1}
    assert os.listdir(tmp_path) == ["r.json"]


def test_write_json_unwritable_directory(tmp_path, capsys):
    """The directory cannot be made (a file stands where it should be): one line, exit 3."""
    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit) as info:
        cli.write_json(str(tmp_path / "file" / "r.json"), {})
    assert info.value.code == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: cannot write")


@pytest.mark.parametrize("path, message", [("{tmp}", "is a directory"),
                                           ("{tmp}/f.txt", "must end in .npz"),
                                           ("", "needs a file path")])
def test_check_output_file(path, message, tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.check_output_file(_parser(), "--out", path.replace("{tmp}", str(tmp_path)), ".npz")
    assert message in capsys.readouterr().err
