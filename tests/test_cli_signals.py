"""One Ctrl-C (SIGINT to the process group, as a terminal sends it) or one SIGTERM (to the main process, as ``kill``
and service managers send it) stops a command within 10 s: every process of the run is gone (no worker left under
PID 1), the exit status is 130 / 143 with a one-line message, and nothing half-written is left (no output folder, no
``.part`` file, no staging folder).

The commands run as real subprocesses in their own session; the signal is sent once the work is under way (the
pool's workers exist, or the temporary ``.part`` output exists)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

psutil = pytest.importorskip("psutil")

PROJECT_ROOT = Path(__file__).resolve().parents[1]
#: the program, with SIGINT at its default (a test runner may start children with SIGINT ignored)
LAUNCH = (
    "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "from magnav_ins.cli import main; sys.exit(main(sys.argv[1:]))"
)
STOP_WITHIN_S = 10.0

#: a study whose runs each take several seconds (UKF + MLR on the shipped gravity map, 3000 s at 10 Hz)
SLOW = """\
name = "slow"
seed = 1
runs = 6

[trajectory]
kind = "great_circle"
start = [-38.0, 144.5]
end = [-35.0, 150.0]
altitude_m = 10000.0
speed_mps = 22.0
duration_s = 3000.0

[imu]
grade = "precision"
rate_hz = 10.0

[map]
path = "builtin:eigen6c4-australia-se"
kind = "gravity_disturbance_mgal"

[sensor]
kind = "gravimeter"
sigma = 1.0
interval_s = 10.0

[[estimator]]
name = "mlr+ukf"
matcher = { kind = "mlr" }
window = 10
fusion = { kind = "ukf" }
"""


def _start(argv: list[str], cwd: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(PROJECT_ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen(
        [sys.executable, "-c", LAUNCH, *argv],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def _wait_for(cond, timeout: float, proc: subprocess.Popen, what: str) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"the command ended (status {proc.returncode}) before {what}: {err[-2000:]}")
        time.sleep(0.1)
    _kill_all(proc)
    pytest.fail(f"timed out waiting for {what}")


def _family(proc: subprocess.Popen) -> list:
    try:
        return [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def _busy_workers(proc: subprocess.Popen, cpu_s: float = 1.0) -> int:
    """Worker processes that have spent ``cpu_s`` of CPU: inside a run (a run takes longer)."""
    n = 0
    for p in _family(proc)[1:]:
        try:
            n += p.cpu_times().user >= cpu_s
        except psutil.NoSuchProcess:
            pass
    return n


def _kill_all(proc: subprocess.Popen) -> None:
    for p in _family(proc):
        try:
            p.kill()
        except psutil.NoSuchProcess:
            pass
    proc.wait(5)


def _signal_and_check(proc: subprocess.Popen, sig: int, to_group: bool, expected_status: int) -> str:
    """Send ``sig``; within STOP_WITHIN_S the command and every process it started must be gone. Returns stderr."""
    family = _family(proc)
    if to_group:
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    t0 = time.monotonic()
    try:
        _, err = proc.communicate(timeout=STOP_WITHIN_S)
    except subprocess.TimeoutExpired:
        for p in family:
            try:
                p.kill()
            except psutil.NoSuchProcess:
                pass
        pytest.fail(f"the command or a process it started still ran {STOP_WITHIN_S} s after signal {sig}")
    gone, alive = psutil.wait_procs(family, timeout=max(0.1, STOP_WITHIN_S - (time.monotonic() - t0)))
    for p in alive:  # pragma: no cover - only on failure
        p.kill()
    assert not alive, f"processes left after signal {sig}: {[p.pid for p in alive]}"
    assert proc.returncode == expected_status, err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("magnav-ins: "), err
    assert "Traceback" not in err
    return lines[0]


def _leftovers(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if ".part" in p.name or "staging" in p.name)


# ------------------------------------------------------------------------------------------------ run --jobs 2
@pytest.mark.parametrize(
    ("sig", "to_group", "status", "message"),
    [(signal.SIGINT, True, 130, "interrupted"), (signal.SIGTERM, False, 143, "terminated")],
    ids=["ctrl-c", "sigterm"],
)
def test_run_jobs_2_stops_on_one_signal(tmp_path, sig, to_group, status, message):
    (tmp_path / "slow.toml").write_text(SLOW)
    proc = _start(["run", "slow.toml", "--jobs", "2", "--out", "out", "--quiet", "--no-plots"], tmp_path)
    _wait_for(lambda: _busy_workers(proc) >= 2, 90.0, proc, "both workers inside a run")
    line = _signal_and_check(proc, sig, to_group, status)
    assert message in line
    assert not (tmp_path / "out").exists()
    assert _leftovers(tmp_path) == []


# ------------------------------------------------------------------------------------------------ run on Dask
def test_run_on_dask_stops_on_ctrl_c_and_frees_the_cluster(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    (tmp_path / "slow.toml").write_text(SLOW)
    with (
        distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl,
        distributed.Client(cl) as client,
    ):
        proc = _start(
            ["run", "slow.toml", "--scheduler", cl.scheduler_address, "--out", "out", "--quiet", "--no-plots"],
            tmp_path,
        )
        _wait_for(lambda: any(client.processing().values()), 60.0, proc, "runs on the cluster")
        time.sleep(1.0)
        assert "interrupted" in _signal_and_check(proc, signal.SIGINT, True, 130)
        # the study's runs were withdrawn from the cluster: nothing queued or processing a moment later
        t_end = time.monotonic() + STOP_WITHIN_S
        while time.monotonic() < t_end and client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)):
            time.sleep(0.2)
        assert client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) == 0
    assert not (tmp_path / "out").exists()
    assert _leftovers(tmp_path) == []


# ------------------------------------------------------------------------------------------------ ins integrate
@pytest.fixture(scope="module")
def long_imu(tmp_path_factory) -> tuple[Path, Path]:
    """600,000 samples (100 Hz, 100 min) at rest, and the initial state."""
    d = tmp_path_factory.mktemp("imu")
    imu = d / "imu.csv"
    with imu.open("w") as fh:
        fh.write("t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n")
        fh.writelines(f"{k / 100:.2f},0,0,0,0,0,-9.80\n" for k in range(600_000))
    init = d / "init.json"
    init.write_text(
        textwrap.dedent("""\
        {"t": 0.0, "lat_deg": 40.0, "lon_deg": -84.0, "h_m": 200.0, "v_n": [0, 0, 0],
         "roll_deg": 0.0, "pitch_deg": 0.0, "yaw_deg": 0.0}""")
    )
    return imu, init


@pytest.mark.parametrize(
    ("sig", "to_group", "status"), [(signal.SIGTERM, False, 143), (signal.SIGINT, True, 130)], ids=["sigterm", "ctrl-c"]
)
def test_ins_integrate_leaves_no_part_file(tmp_path, long_imu, sig, to_group, status):
    imu, init = long_imu
    proc = _start(
        ["ins", "integrate", str(imu), "--init", str(init), "--out", "traj.csv", "--chunk-rows", "2000"], tmp_path
    )
    _wait_for(lambda: any(tmp_path.glob(".traj.csv.*.part")), 60.0, proc, "the temporary output was opened")
    time.sleep(0.3)
    _signal_and_check(proc, sig, to_group, status)
    assert not (tmp_path / "traj.csv").exists()
    assert list(tmp_path.iterdir()) == []
