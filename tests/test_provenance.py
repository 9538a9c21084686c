"""Tests of torchrl_ftb.provenance: the commit a results file records is the code that ran."""
from __future__ import annotations

import shutil
import subprocess

import pytest

from torchrl_ftb import provenance
from torchrl_ftb.testing import load_script


def _git(repo, *args: str) -> None:
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@example.com", *args], cwd=repo, check=True,
                   capture_output=True, text=True)


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_git_commit_is_the_commit_the_code_was_loaded_from(tmp_path):
    # a checkout holding a copy of the module: load it, then commit again in the same tree, as a session
    # does while an hour-long recipe runs; the recipe must still record the commit it started with
    _git(tmp_path, "init", "-q")
    shutil.copy(provenance.__file__, tmp_path / "provenance.py")
    _git(tmp_path, "add", "provenance.py")
    _git(tmp_path, "commit", "-qm", "one")
    module = load_script(tmp_path / "provenance.py", "provenance_copy")
    started = module.git_commit()
    (tmp_path / "notes.txt").write_text("later work\n")
    _git(tmp_path, "add", "notes.txt")
    _git(tmp_path, "commit", "-qm", "two")
    now = module.git_commit(tmp_path)
    assert started is not None and len(started) == 40 and len(now) == 40
    assert now != started and module.git_commit() == started
