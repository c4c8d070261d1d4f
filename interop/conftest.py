"""Shared helpers for the interoperability tests: the rollbase binaries and the processes
they run (bridge, simulator, controller), always stopped at the end of a test."""

import os
import re
import signal
import subprocess
import time
from pathlib import Path

import cantools
import pytest

REPO = Path(__file__).resolve().parent.parent
BIN_DIR = Path(os.environ.get("ROLLBASE_BIN_DIR", REPO / "target" / "release"))


def binary(name: str) -> Path:
    path = BIN_DIR / name
    if not path.exists():
        raise FileNotFoundError(
            f"{path} is missing: build it first with `cargo build --release --workspace --bins` "
            "(or point ROLLBASE_BIN_DIR at the directory holding rollbase and rollbase-sim)"
        )
    return path


def rollbase(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    """Runs `rollbase ARGS…` to completion and returns it (stdout/stderr as text)."""
    return subprocess.run(
        [str(binary("rollbase")), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


class Proc:
    """A background process whose stderr goes to a file; `stop()` sends SIGINT (a clean
    stop with a summary) and returns the stderr text."""

    def __init__(self, args, log: Path):
        self.log = log
        self._f = open(log, "w")
        self.p = subprocess.Popen(
            [str(a) for a in args], stdout=self._f, stderr=subprocess.STDOUT, text=True
        )

    def text(self) -> str:
        self._f.flush()
        return self.log.read_text()

    def wait_for(self, pattern: str, timeout: float = 10.0) -> re.Match:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            m = re.search(pattern, self.text())
            if m:
                return m
            if self.p.poll() is not None:
                break
            time.sleep(0.02)
        raise AssertionError(f"{self.p.args[0]} never printed /{pattern}/:\n{self.text()}")

    def stop(self, timeout: float = 10.0) -> str:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
            try:
                self.p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(timeout=5)
        self._f.close()
        return self.log.read_text()


@pytest.fixture
def procs():
    """Collects background processes and stops every one of them when the test ends."""
    started = []

    def start(args, log):
        p = Proc(args, log)
        started.append(p)
        return p

    yield start
    for p in reversed(started):
        p.stop()


@pytest.fixture
def bridge(procs, tmp_path):
    """A `rollbase bridge` on a free loopback port; yields (host, port, Proc)."""
    b = procs([binary("rollbase"), "bridge", "--listen", "127.0.0.1:0"], tmp_path / "bridge.log")
    m = b.wait_for(r"listening on (127\.0\.0\.1):(\d+)")
    return m.group(1), int(m.group(2)), b


@pytest.fixture(scope="session")
def dbc_db(tmp_path_factory):
    """cantools' view of `rollbase dbc`."""
    out = rollbase("dbc")
    assert out.returncode == 0, out.stderr
    path = tmp_path_factory.mktemp("dbc") / "rollbase.dbc"
    path.write_text(out.stdout)
    return cantools.database.load_file(str(path))


def crc8_j1850(data: bytes) -> int:
    """CRC-8 SAE J1850: poly 0x1D, init 0xFF, xorout 0xFF, not reflected (written here
    independently of rollbase's implementation)."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def frame_crc_ok(can_id: int, data: bytes) -> bool:
    """The rollbase end-to-end CRC: over [id & 0xFF, id >> 8, payload without the CRC byte]."""
    return len(data) >= 1 and crc8_j1850(bytes([can_id & 0xFF, can_id >> 8]) + data[:-1]) == data[-1]


def with_crc(can_id: int, payload: bytes) -> bytes:
    """`payload` with its last byte replaced by the rollbase CRC."""
    body = bytes(payload[:-1])
    return body + bytes([crc8_j1850(bytes([can_id & 0xFF, can_id >> 8]) + body)])
