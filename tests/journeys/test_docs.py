"""The README and docs/ run: each ``sh`` block through the installed commands, each quoted
figure checked (:mod:`journeys.docrunner` says how blocks are marked)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from journeys.docrunner import Block, blocks
from journeys.harness import REPO, Installed, source_files

DOCS = sorted(
    [REPO / "README.md", *REPO.glob("docs/*.md"), *REPO.glob("firmware/**/*.md"),
     *REPO.glob("drivers/**/*.md"), *REPO.glob("sessions/**/*.md")]
)  # fmt: skip
BLOCKS = [b for doc in DOCS for b in blocks(doc)]
STARTS_A_BENCH = re.compile(r"--mock\b|--port\b|\bmake run\b|\bsmabench (mock|demo|gui)\b")
"""A block with this in its script runs a real-time bench: it joins the ``realtime_bench`` tests
(tests/conftest.py); the analysis blocks run beside them."""


def _param(block: Block):
    marks = [pytest.mark.realtime_bench] if STARTS_A_BENCH.search(block.script) else []
    return pytest.param(block, id=block.name, marks=marks)


def scratch_checkout(dest: Path) -> Path:
    """A copy of the checkout's files at ``dest/repo`` (commands write where the docs say),
    with the workplace's ``shared`` folder beside it when there is one (``../shared``)."""
    root = dest / "repo"
    for rel in source_files(REPO):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, root / rel)
    shared = REPO.parent / "shared"
    if shared.is_dir():
        (dest / "shared").symlink_to(shared)
    return root


def test_every_block_is_found_and_well_formed():
    assert len(BLOCKS) >= 5, [b.name for b in BLOCKS]
    for b in BLOCKS:
        assert b.script.strip(), f"{b.name}: empty sh block"


@pytest.mark.slow
@pytest.mark.timeout(1800)  # the block's own limit (doc-run: timeout) is the subprocess's
@pytest.mark.parametrize("block", [_param(b) for b in BLOCKS])
def test_doc_block_runs(installed: Installed, tmp_path: Path, block: Block) -> None:
    if block.skip:
        pytest.skip(f"{block.name}: {block.skip}")
    if "../shared" in block.script and not (REPO.parent / "shared").is_dir():
        pytest.skip(f"{block.name}: needs the workplace's shared data beside the checkout")
    root = scratch_checkout(tmp_path)
    proc = subprocess.run(
        ["bash", "-e", "-o", "pipefail", "-c", block.script], cwd=root, capture_output=True,
        text=True, timeout=block.timeout_s, env=installed.env(), stdin=subprocess.DEVNULL,
    )  # fmt: skip
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"{block.name} exited {proc.returncode}:\n{output[-4000:]}"
    assert "Traceback" not in output, output[-4000:]
    problems = [why for check in block.checks if (why := check.verify(output))]
    assert not problems, f"{block.name}: " + "; ".join(problems) + f"\n{output[-3000:]}"
