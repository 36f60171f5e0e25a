"""The benchmarks' baseline tree: a git revision exported for the run, or a checkout's folder."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools" / "bench"))

from _common import baseline_tree, trees_to_compare  # noqa: E402


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="needs the git repository")
def test_a_revision_is_exported_once_and_a_folder_is_taken_as_it_is(tmp_path: Path) -> None:
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    trees = trees_to_compare(ROOT, head)
    exported = trees["baseline"]
    assert trees["this_tree"] == ROOT and exported != ROOT
    assert (exported / "labrig" / "__init__.py").read_text() == (ROOT / "labrig" / "__init__.py").read_text()
    assert baseline_tree(ROOT, head) is exported  # once per process
    assert baseline_tree(ROOT, exported) == exported.resolve()  # a checkout's folder
    assert "baseline" not in trees_to_compare(ROOT, None)
    with pytest.raises(SystemExit, match="neither a folder nor a git revision"):
        baseline_tree(ROOT, "no-such-revision-of-labrig")
    with pytest.raises(SystemExit, match="not a labrig checkout"):
        baseline_tree(ROOT, tmp_path)
