"""Progress bars on a terminal: visible on fit, diagnose, diagnose --auto, import and sweep; absent
with --quiet and off stdout with --json.

Each command runs in a real process whose stderr is a pseudo-terminal (``os.openpty``) and whose
stdout is a pipe, as in a shell with ``> result.json``.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
from pathlib import Path

import pytest


def run_on_tty(argv: list[str], cwd: Path) -> tuple[int, str, str]:
    """(exit status, stdout, what the terminal on stderr received)."""
    master, slave = os.openpty()
    env = {**os.environ, "TERM": "xterm-256color", "COLUMNS": "120", "PYTHONWARNINGS": "ignore"}
    env.pop("NO_COLOR", None)
    proc = subprocess.Popen([sys.executable, "-m", "hilbench.cli", *argv], stdout=subprocess.PIPE, stderr=slave,
                            stdin=subprocess.DEVNULL, cwd=cwd, env=env)
    os.close(slave)
    received = bytearray()
    while True:
        ready, _, _ = select.select([master], [], [], 0.2)
        if ready:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # EIO: the process closed the terminal
                break
            if not chunk:
                break
            received += chunk
        elif proc.poll() is not None:
            break
    os.close(master)
    out = proc.stdout.read().decode() if proc.stdout else ""
    proc.wait(timeout=600)
    return proc.returncode, out, received.decode("utf-8", "replace")


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("progress")
    status, _, err = run_on_tty(["sweep", "piezo-demo", "-o", "demo.h5", "-q"], folder)
    assert status == 0, err
    rows = "\n".join(f"{k / 1000:.4f},{(k % 200) / 20:.4f},{(k % 200) / 10:.4f}" for k in range(3000))
    (folder / "data.csv").write_text("time[s],input[V],output[µm]\n" + rows + "\n", encoding="utf-8")
    return folder


CASES = {
    "sweep": (["sweep", "gmm-issf-duhem", "-e", "sine:amplitude=1|2,frequency_hz=1,cycles=2", "-o", "s.h5"], "run 1"),
    "import": (["import", "data.csv", "-o", "imported.h5"], "import"),
    "fit": (["fit", "demo.h5", "--model", "pmpi"], "fit pmpi"),
    "diagnose": (["diagnose", "demo.h5", "--model", "pi"], "diagnose pi"),
    "diagnose --auto": (["diagnose", "demo.h5", "--model", "pi", "--auto"], "diagnose --auto"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_progress_on_a_terminal(work, name):
    argv, text = CASES[name]
    argv = [a.replace(".h5", f"-{name.replace(' ', '')}.h5") if a in ("s.h5", "imported.h5") else a for a in argv]
    status, out, terminal = run_on_tty([*argv, "--json"], work)
    assert status == 0, terminal
    assert text in terminal, terminal[-2000:]  # the bar's description reached the terminal
    document = json.loads(out)  # stdout holds the JSON document only: no progress there
    assert isinstance(document, (dict, list))


@pytest.mark.parametrize("name", ["import", "fit", "sweep"])
def test_quiet_shows_no_progress(work, name):
    argv, text = CASES[name]
    argv = [a.replace(".h5", "-quiet.h5") if a in ("s.h5", "imported.h5") else a for a in argv]
    status, _, terminal = run_on_tty([*argv, "--quiet"], work)
    assert status == 0, terminal
    assert text not in terminal and "\x1b[?25l" not in terminal  # no bar, no cursor hiding


def test_no_progress_when_stderr_is_not_a_terminal(work):
    proc = subprocess.run([sys.executable, "-m", "hilbench.cli", "import", "data.csv", "-o", "piped.h5"],
                          cwd=work, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
