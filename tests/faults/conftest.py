"""What the fault tests share: the `cosim` command run as a user runs it (a subprocess with its own TMPDIR),
and the checks every such test makes: one clear line and the exit code, no traceback, a folder unchanged,
nothing of ours left in the temporary folder.

Use the `cli` fixture (a `Cli` on the test's tmp_path) or, in a wider-scoped fixture, `Cli(folder)`
through the `cli_class` fixture."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SMOKE = str(ROOT / "configs" / "smoke.yaml")


def _default_sigint() -> None:
    # A shell starts background jobs with SIGINT ignored, and Python keeps it ignored: give the command the
    # terminal's default, as when a user presses Ctrl-C.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Cli:
    """`cosim` commands run in `folder` (their working directory), with `folder/tmpdir` as TMPDIR."""

    SMOKE = SMOKE

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.tmpdir = self.folder / "tmpdir"
        self.tmpdir.mkdir(parents=True, exist_ok=True)

    @staticmethod
    def cmd(*args: str) -> list[str]:
        return [sys.executable, "-m", "cosim.cli", *args]

    @staticmethod
    def settings(*pairs: str) -> list[str]:
        """`--set` options, one per KEY=VALUE."""
        return [a for kv in pairs for a in ("--set", kv)]

    def env(self) -> dict[str, str]:
        return {**os.environ, "TMPDIR": str(self.tmpdir)}

    def run(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
        return subprocess.run(self.cmd(*args), cwd=self.folder, capture_output=True, text=True, timeout=timeout,
                              env=self.env())

    def start(self, *args: str) -> subprocess.Popen[str]:
        """The command in the background, stdout and stderr merged, Ctrl-C (SIGINT) as on a terminal."""
        return subprocess.Popen(self.cmd(*args), cwd=self.folder, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env=self.env(), preexec_fn=_default_sigint)

    def no_leftovers(self) -> bool:
        """No temporary folder or file of ours left (torch keeps its own caches there, which are not ours)."""
        return not self.leftovers()

    def leftovers(self) -> list[Path]:
        return [p for p in self.tmpdir.iterdir() if p.name.startswith(("cosim", "pymp-"))]

    @staticmethod
    def assert_clean_error(proc: subprocess.CompletedProcess[str], expected: str, code: int = 2) -> None:
        """Exit `code`, no traceback, exactly one ERROR line, and it contains `expected`."""
        err = proc.stdout + proc.stderr
        assert proc.returncode == code, err
        assert "Traceback" not in err, err
        errors = [line for line in err.splitlines() if " ERROR " in line]
        assert len(errors) == 1 and expected in errors[0], err

    @staticmethod
    def folder_state(folder: Path) -> dict[str, str]:
        """Every file under `folder` with its content's hash."""
        return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(folder.rglob("*")) if p.is_file()}

    @staticmethod
    def wait_for(proc: subprocess.Popen[str], text: str, timeout: float = 240) -> list[str]:
        """Lines of proc's output up to the first containing `text`; the test fails (and proc is killed) without."""
        lines, end = [], time.monotonic() + timeout
        assert proc.stdout is not None
        while time.monotonic() < end:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if text in line:
                return lines
        proc.kill()
        pytest.fail(f"no {text!r} in: {''.join(lines)}")

    @staticmethod
    def finish(proc: subprocess.Popen[str], timeout: float = 120) -> str:
        """The rest of proc's output once it exits; a hung command must not outlive its test."""
        try:
            return proc.communicate(timeout=timeout)[0]
        finally:
            proc.kill()

    @staticmethod
    def children(pid: int) -> list[int]:
        out = []
        for task in Path(f"/proc/{pid}/task").iterdir():
            out += [int(c) for c in (task / "children").read_text().split()]
        return out

    @classmethod
    def workers(cls, proc: subprocess.Popen[str]) -> list[int]:
        """Worker pids: grandchildren of the command (its forkserver's children)."""
        return [g for c in cls.children(proc.pid) for g in cls.children(c)]


@pytest.fixture
def cli(tmp_path: Path) -> Cli:
    return Cli(tmp_path)


@pytest.fixture(scope="session")
def cli_class() -> type[Cli]:
    return Cli
