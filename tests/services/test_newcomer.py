"""What a new user meets: a report on every scenario, prompt failure instead of a hang,
one line instead of a traceback, and no silent nonsense run (each fails on the old bug)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import ROOT


def zf(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL)


# 1. eval --report on the many-target scenarios ---------------------------------------------
@pytest.mark.parametrize("args", [("--scenario", "df-multi", "--methods", "EKF"),
                                  ("--scenario", "air-picture", "--methods", "SS", "--duration-s", "8")])
def test_report_of_a_many_target_evaluation(tmp_path, args):
    pytest.importorskip("matplotlib")
    p = zf("eval", *args, "--runs", "1", "--report", str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr
    text = (tmp_path / "report.md").read_text()
    assert "gospa.png" in text and (tmp_path / "gospa.png").stat().st_size > 1000
    assert "rmse_pos.png" not in text  # no empty RMSE panel for a run that has none


# 2. a child that fails ends the run ---------------------------------------------------------
FAILING_SENSOR = """
import sys
import services.supervisor as supervisor
start = supervisor.Children.start
def failing(self, name, argv):  # the radar's emulator fails at its first scan, as with a bad seed
    if name == "radar2d":
        argv = [*argv, "--seed", "-1"]
    start(self, name, argv)
supervisor.Children.start = failing
from services.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_failing_child_ends_the_run_promptly_with_its_message(tmp_path):
    import time

    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", FAILING_SENSOR, "run", "--scenario", "patent-3d", "--speed", "max",
                        "--rrd", str(tmp_path / "r.rrd")], capture_output=True, text=True, timeout=120,
                       stdin=subprocess.DEVNULL)
    assert time.monotonic() - t0 < 90  # it hung for ever before (a start under load takes ~30 s)
    assert p.returncode == 1, p.stderr[-2000:]
    last = p.stderr.strip().splitlines()[-1]
    assert last.startswith("zfusion run: radar2d failed (exit ") and "seed" in last, last


# 3. every user error is one line -------------------------------------------------------------
def _free_port() -> int:
    from services.launcher import free_port

    return free_port()


def _typo_scenario(tmp_path):
    from pathlib import Path

    import sensors_sim

    text = (Path(sensors_sim.__file__).parent / "scenarios" / "patent-3d.toml").read_text()
    text = text.replace("\nq = 0.01 ", "\nqq = 0.01", 1)  # the [tracker] key q misspelt
    path = tmp_path / "typo.toml"
    path.write_text(text)
    return path


NO_MATPLOTLIB = "import sys; sys.modules['matplotlib'] = None; from services.cli import main; sys.exit(main(sys.argv[1:]))"

MISTAKES = {  # name: (argv with {tmp}, {port}, {typo}, exit code, what the line says)
    "scenario-file": (["run", "--scenario", "{tmp}/bad.toml", "--speed", "max"], 2, "bad.toml"),
    "scenario-file-eval": (["eval", "--scenario", "{tmp}/bad.toml", "--runs", "1"], 2, "bad.toml"),
    "unknown-method": (["run", "--scenario", "patent-3d", "--method", "FOO"], 2, "unknown method 'FOO'"),
    "tracker-key-typo": (["run", "--scenario", "{typo}", "--speed", "max"], 2, "'qq'"),
    "df-method-on-3d": (["run", "--scenario", "patent-3d", "--method", "EKF"], 2, "DF (bearings-only)"),
    "missing-zenoh-config": (["run", "--scenario", "patent-3d", "--zenoh-config", "{tmp}/no.json5"], 2,
                             "--zenoh-config"),
    "refused-connection": (["sensor", "--scenario", "patent-3d", "--id", "radar2d", "--zenoh-mode", "client",
                            "--connect", "tcp/127.0.0.1:{port}"], 1, "nothing answers there"),
    "bad-listen-port": (["router", "--listen", "tcp/127.0.0.1:notaport"], 2, "invalid port"),
    "missing-tls-key": (["router", "--zenoh-config", "deploy/zenoh/router-tls-acl.json5",
                         "--listen", "tls/127.0.0.1:{port}"], 2, "private key"),
    "report-without-matplotlib": (["-c", NO_MATPLOTLIB, "eval", "--scenario", "patent-3d", "--runs", "1",
                                   "--report", "{tmp}/r"], 2, "pip install 'zfusion[report]'"),
    "unwritable-report": (["eval", "--scenario", "patent-3d", "--runs", "1", "--report", "/etc/passwd/r"], 2,
                          "cannot write there"),
    "negative-seed": (["run", "--scenario", "patent-3d", "--seed", "-1"], 2, "non-negative"),
    # 4. what used to run and give nonsense in silence
    "sensor-kind-missing": (["run", "--scenario", "patent-3d", "--method", "RADAR3D"], 2, "az_el_range"),
    "two-targets-no-association-run": (["run", "--scenario", "{two}", "--speed", "max"], 2, "association"),
    "two-targets-no-association-eval": (["eval", "--scenario", "{two}", "--runs", "1"], 2, "association"),
    "unreachable-connect": (["run", "--scenario", "patent-3d", "--speed", "max", "--connect",
                             "tcp/127.0.0.1:{port}"], 1, "nothing accepts a connection"),
}


def _two_targets(tmp_path):
    from pathlib import Path

    import sensors_sim

    text = (Path(sensors_sim.__file__).parent / "scenarios" / "patent-3d.toml").read_text()
    path = tmp_path / "two.toml"
    path.write_text(text + '\n[targets.T2]\npos_m = [7000.0, 9000.0, 2500.0]\nvel_mps = [-120.0, -60.0, 5.0]\n'
                    'acc_mps2 = [0.5, 1.0, -0.05]\njerk_psd = 0.01\n')
    return path


@pytest.mark.parametrize("case", list(MISTAKES))
def test_a_user_mistake_is_one_line(tmp_path, case):
    import os

    argv, code, says = MISTAKES[case]
    (tmp_path / "bad.toml").write_text('name = "bad"\nduration = 10\n')
    subs = {"{tmp}": str(tmp_path), "{port}": str(_free_port()), "{typo}": str(_typo_scenario(tmp_path)),
            "{two}": str(_two_targets(tmp_path))}
    for k, v in subs.items():
        argv = [a.replace(k, v) for a in argv]
    cmd = [sys.executable, *argv] if argv[0] == "-c" else [sys.executable, "-m", "services.cli", *argv]
    root = ROOT
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL, cwd=root,
                       env={**os.environ, "PYTHONPATH": str(root)})
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert "Traceback" not in p.stderr, p.stderr[-3000:]
    assert p.returncode == code, (p.returncode, p.stderr)
    assert len(lines) == 1 and lines[0].startswith("zfusion ") and says in lines[0], p.stderr


# 6. output ---------------------------------------------------------------------------------
def test_the_table_keeps_its_columns_apart_and_explains_the_bound():
    from services.summary import format_table

    m = {"rmse_pos": 28138.939827, "rmse_vel": 390.4548, "rmse_acc": 15.999999999999998, "cep50": None,
         "anees": 2.1e6, "n_updates": 31}
    doc = {"scenario": "s", "topology": "centralised", "fusion_rule": None, "seed": 1, "runs": 1,
           "methods": {"RADAR2D": m, "SS": {**m, "rmse_pos": 16.94}},
           "crb": {"overall": {"rmse_pos": 16.79, "rmse_vel": 311.87, "rmse_acc": 45.27}}}
    lines = format_table(doc).splitlines()
    assert "fusion rule" not in lines[0]
    head = lines[1].split()
    for line in lines[2:4]:
        cells = line.split()
        assert len(cells) == len(head), line  # 28138.9398390.4548 ran together
        assert float(cells[1]) == pytest.approx(m["rmse_pos"] if cells[0] == "RADAR2D" else 16.94, rel=1e-5)
        assert cells[3] == "16.0000" and cells[5] == "2.100e+06"
    crb = next(i for i, ln in enumerate(lines) if ln.startswith("CRB "))
    assert "first scans" in lines[crb + 1]  # why a filter's velocity error can be below the bound


def test_view_checks_the_file_and_the_display_first(tmp_path):
    from services.commands.view import viewer_argv
    from services.errors import UserError

    good, bad = tmp_path / "good.rrd", tmp_path / "bad.rrd"
    good.write_bytes(b"RRF2" + bytes(60))
    bad.write_bytes(b"not a recording")
    for path, env, code, says in ((tmp_path / "none.rrd", {"DISPLAY": ":0"}, 2, "no such recording"),
                                  (bad, {"DISPLAY": ":0"}, 2, "not a Rerun recording"),
                                  (good, {}, 1, "no display")):
        with pytest.raises(UserError, match=says) as e:
            viewer_argv(str(path), env)
        assert e.value.code == code and "\n" not in str(e.value)
    argv = viewer_argv(str(good), {"DISPLAY": ":0"})
    assert argv[1:] == ["--bind", "127.0.0.1", str(good)]  # its port on loopback, not on every interface
    p = zf("view", str(bad))
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr


@pytest.mark.parametrize("delay", [0.3, 1.0, 2.0])
def test_ctrl_c_in_the_first_seconds_prints_no_traceback(tmp_path, delay):
    """Ctrl-C at a terminal signals the whole foreground process group: the launcher and
    its children still starting. Only the launcher's one line may come out."""
    import os
    import signal
    import time

    p = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--scenario", "patent-3d", "--speed", "max",
                          "--rrd", str(tmp_path / "r.rrd")], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, process_group=0)
    import psutil

    deadline = time.monotonic() + 60
    while not psutil.Process(p.pid).children() and time.monotonic() < deadline:
        time.sleep(0.05)  # the launcher is up and has started its first child
    time.sleep(delay)  # its children are still importing, or just started
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]
    assert p.returncode in (130, 0), err[-2000:]


@pytest.mark.parametrize("delay", [0.3, 1.5])
def test_sigint_stops_a_run_that_inherited_it_ignored(delay):
    """A shell script's background job starts with SIGINT ignored: ``kill -INT`` still stops
    the installed ``zfusion`` command, sent while it is importing (0.3 s) or starting up,
    with 130 or 0 and no traceback. The run is endless: ignoring the signal fails here."""
    import os
    import signal
    import time
    from pathlib import Path

    zfusion_cmd = Path(sys.executable).with_name("zfusion")
    p = subprocess.Popen([str(zfusion_cmd), "run", "--scenario", "patent-3d-orbit", "--live"],
                         stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        time.sleep(delay)
        os.kill(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.terminate()
            p.communicate(timeout=60)
    assert p.returncode in (130, 0), err[-2000:]
    assert "Traceback" not in err, err[-3000:]


def test_eval_progress_shows_at_once_with_a_time_estimate():
    p = zf("eval", "--scenario", "thesis-fixed-c1", "--runs", "3", "--methods", "EKF", "--progress")
    steps = [s.strip() for s in p.stderr.split("\r") if s.strip()]
    assert p.returncode == 0 and steps[0].startswith("thesis-fixed-c1: run 0/3")  # before the first run ends
    assert any("run 1/3" in s and " left" in s for s in steps), steps
    q = zf("eval", "--scenario", "thesis-fixed-c1", "--runs", "1", "--methods", "EKF")
    assert q.stderr == ""  # quiet when stderr is not a terminal


def test_run_shows_progress_on_a_terminal_only(tmp_path):
    import os
    import pty

    master, slave = pty.openpty()
    p = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--scenario", "patent-3d", "--speed", "3",
                          "--duration-s", "6", "--rrd", str(tmp_path / "r.rrd")], stdin=subprocess.DEVNULL,
                         stdout=subprocess.DEVNULL,
                         stderr=slave)
    os.close(slave)
    seen = b""
    while True:
        try:
            chunk = os.read(master, 4096)
        except OSError:  # the pty closed: the run ended
            break
        if not chunk:
            break
        seen += chunk
    assert p.wait(120) == 0
    assert b"patent-3d: t = " in seen and b" updates" in seen, seen[-2000:]
