"""``python -m device.pi run`` (device/pi/__main__.py): it runs on simulated hardware,
refuses bad artefacts, config and sources with exit status 2 and one line naming the
problem, and a missing live camera or IMU is a fault, not an exit (until SIGTERM)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from device.pi.__main__ import main


def _run_main(args, capsys):
    rc = main(["run", "--imu", "none", "--serial", "loop://", "--frames", "2"] + args)
    return rc, capsys.readouterr().err


def test_bad_artefacts_refuse_to_start_with_exit_2(model_dir, tmp_path, capsys):
    import shutil
    cam = ["--camera", "sim://press-hard"]
    # malformed manifest
    bad = tmp_path / "m1"
    shutil.copytree(model_dir, bad)
    (bad / "surface" / "manifest.json").write_text("{not json")
    rc, err = _run_main(cam + ["--models", str(bad)], capsys)
    assert rc == 2 and "surface/manifest.json" in err and "corrupt manifest" in err
    # truncated model file (checksum)
    bad = tmp_path / "m2"
    shutil.copytree(model_dir, bad)
    f = bad / "surface" / "model.int8.onnx"
    f.write_bytes(f.read_bytes()[:100])
    rc, err = _run_main(cam + ["--models", str(bad)], capsys)
    assert rc == 2 and "model.int8.onnx" in err and "checksum" in err
    # a model for another pin layout
    from tests.windows import synthetic

    from host.learn.train import train_model
    bad = tmp_path / "m3"
    train_model("surface", "fnn", synthetic(n_pins=5, classes=("hard", "soft")),
                out_dir=bad / "surface", progress=False, hidden=(4, 2), epochs=5)
    rc, err = _run_main(cam + ["--models", str(bad)], capsys)
    assert rc == 2 and "manifest.json" in err and "133-pin layout" in err
    # bad config value, bad sources, missing models folder
    cfg = tmp_path / "leg.toml"
    cfg.write_text("[camera]\nfps = -3\n")
    rc, err = _run_main(cam + ["--config", str(cfg)], capsys)
    assert rc == 2 and "camera.fps" in err and "-3" in err
    rc, err = _run_main(["--camera", "bogus://x"], capsys)
    assert rc == 2 and "bogus" in err
    rc, err = _run_main(cam + ["--models", str(tmp_path / "nope")], capsys)
    assert rc == 2 and "nope" in err
    rc = main(["run", "--camera", "sim://press-hard", "--imu", "i2c://1/0x200", "--serial",
               "loop://"])
    assert rc == 2 and "0x200" in capsys.readouterr().err


def test_a_config_that_is_not_toml_a_manifest_of_wrong_types_and_a_portless_socket(
        model_dir, tmp_path, capsys):
    import shutil
    cam = ["--camera", "sim://press-hard"]
    (tmp_path / "folder.toml").mkdir()
    rc, err = _run_main(cam + ["--config", str(tmp_path / "folder.toml")], capsys)
    assert rc == 2 and err.count("\n") == 1 and "folder.toml: is a folder, not a TOML file" in err
    (tmp_path / "latin1.toml").write_bytes(b'[camera]\nname = "caf\xe9"\n')
    rc, err = _run_main(cam + ["--config", str(tmp_path / "latin1.toml")], capsys)
    assert rc == 2 and "latin1.toml: not UTF-8 text" in err
    bad = tmp_path / "m"
    shutil.copytree(model_dir, bad)
    for m in (bad / "surface").glob("manifest*.json"):
        m.write_text(json.dumps(dict(json.loads(m.read_text()), T=1e9)))
    rc, err = _run_main(cam + ["--models", str(bad)], capsys)
    assert rc == 2 and "T must be a whole number of frames in [1, 1000]" in err
    rc = main(["run", "--imu", "none", "--serial", "socket://notahost", "--frames", "2"] + cam)
    assert rc == 2 and "a socket:// URL needs a host and a port" in capsys.readouterr().err


def test_python_dash_m_device_pi_run_on_simulated_hardware(tmp_path):
    status = tmp_path / "st.json"
    r = subprocess.run([sys.executable, "-m", "device.pi", "run", "--camera", "sim://press-hard",
                        "--imu", "sim://press-hard", "--serial", "loop://", "--frames", "25",
                        "--status", str(status), "--json"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["frames"] == 25 and res["packets_sent"] >= 25
    assert res["latency_ms_p50"] is not None and res["latency_ms_p50"] > 0
    assert json.loads(status.read_text())["frames"] == 25


def test_missing_live_camera_is_a_fault_not_an_exit_and_sigterm_stops_cleanly(tmp_path):
    import signal
    status = tmp_path / "st.json"
    p = subprocess.Popen([sys.executable, "-m", "device.pi", "run", "--camera",
                          f"v4l2://{tmp_path / 'video0'}", "--imu", "none", "--serial",
                          "loop://", "--status", str(status), "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        doc = {}
        while time.monotonic() < deadline and "camera" not in doc.get("fault_names", []):
            time.sleep(0.1)
            if status.exists():
                doc = json.loads(status.read_text())
        assert p.poll() is None, "the runtime exited without a camera"
        assert "camera" in doc["fault_names"] and doc["frames"] == 0
        assert doc["packets_sent"] > 0               # HEARTBEAT / FAULT with no frames
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=20)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0
    res = json.loads(out)
    assert res["camera_errors"] >= 1 and res["frames"] == 0


def test_the_runtime_starts_without_its_imu_and_reports_the_fault(tmp_path):
    status = tmp_path / "status.json"
    res = subprocess.run([sys.executable, "-m", "device.pi", "run", "--camera",
                          "sim://press-hard", "--imu", "i2c://97/0x68", "--serial", "loop://",
                          "--frames", "20", "--status", str(status)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "retrying" in res.stderr
    doc = json.loads(status.read_text())
    assert "imu" in doc["fault_names"] and doc["frames"] == 20



def test_status_in_a_missing_folder_and_one_models_folder_refuse_to_start(model_dir, tmp_path,
                                                                           capsys):
    cam = ["--camera", "sim://press-hard"]
    rc, err = _run_main(cam + ["--status", str(tmp_path / "nope" / "st.json")], capsys)
    assert rc == 2 and "--status" in err and "does not exist" in err
    # one model's folder, not the folder of models: it would run the rules alone
    rc, err = _run_main(cam + ["--models", str(model_dir / "surface")], capsys)
    assert rc == 2 and "one model's folder" in err and str(model_dir) in err


def test_no_model_refuses_to_start_unless_rules_only_is_asked(model_dir, tmp_path, capsys,
                                                               monkeypatch):
    """The leg never runs on its rules alone without saying so (issue 32 item 2)."""
    cam = ["--camera", "sim://press-hard"]
    empty = tmp_path / "empty"
    empty.mkdir()
    rc, err = _run_main(cam + ["--models", str(empty)], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("device.pi run: error: no model found in --models ")
    assert str(empty) in err and "--rules-only" in err
    # the default folder missing (an install without models): it names where it looked
    import device.pi.runtime.load as load
    import device.pi.runtime.start as start
    for mod in (load, start):
        monkeypatch.setattr(mod, "default_models_dir", lambda: tmp_path / "site" / "models")
    rc, err = _run_main(cam + ["--json"], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert str(tmp_path / "site" / "models") in err and "--rules-only" in err
    # asked for: it runs, says so in one line, and in the status file and summary
    st = tmp_path / "st.json"
    rc = main(["run", "--imu", "none", "--serial", "loop://", "--frames", "2", "--json",
               "--rules-only", "--status", str(st)] + cam)
    out, err = capsys.readouterr()
    assert rc == 0 and [ln for ln in err.splitlines() if "rules" in ln] == [
        "device.pi run: note: --rules-only: no model loaded; the surface decision comes "
        "from the rules alone (status: rules_only true)"]
    assert json.loads(out)["rules_only"] is True and json.loads(out)["models"] == []
    assert json.loads(st.read_text())["rules_only"] is True
    # with models it says rules_only false; with both options it refuses
    rc, err = _run_main(cam + ["--models", str(model_dir), "--status", str(st)], capsys)
    assert rc == 0 and json.loads(st.read_text())["rules_only"] is False
    rc, err = _run_main(cam + ["--models", str(model_dir), "--rules-only"], capsys)
    assert rc == 2 and "not both" in err and len(err.strip().splitlines()) == 1


def _fill(fd: int) -> None:
    """Write to a non-blocking fd until the kernel takes no more."""
    os.set_blocking(fd, False)
    try:
        while True:
            os.write(fd, b"\0" * 4096)
    except BlockingIOError:
        pass


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="no pty on this system")
def test_a_serial_peer_that_never_reads_raises_the_link_fault_and_sigterm_ends_it(tmp_path):
    """The MCU stops reading: the loop runs on (status refreshed, the link fault set,
    old packets dropped), and SIGTERM ends the process within 1 s. (pyserial's own
    write() froze it here: stale status, no fault, SIGTERM ignored.)"""
    import signal
    import tty
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    _fill(slave)                     # the buffer an MCU that stopped reading left full
    status = tmp_path / "st.json"
    p = subprocess.Popen([sys.executable, "-m", "device.pi", "run", "--camera",
                          "sim://walk?realtime=1", "--imu", "none", "--serial",
                          os.ttyname(slave), "--status", str(status), "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        docs = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and p.poll() is None:
            time.sleep(0.1)
            try:
                doc = json.loads(status.read_text())
            except (OSError, ValueError):
                continue
            if "link" in doc["fault_names"] and doc["frames"] > 0:
                docs.append(doc)
            if len(docs) >= 12:                     # >= 1.2 s with the link full
                break
        assert p.poll() is None, p.stderr.read()
        assert len(docs) >= 12, "no status with the link fault"
        assert docs[-1]["frames"] > docs[0]["frames"]         # frames go on
        assert docs[-1]["t_unix"] > docs[0]["t_unix"]         # the file is refreshed
        assert time.time() - docs[-1]["t_unix"] < 1.5
        assert docs[-1]["packets_dropped"] > docs[0]["packets_dropped"]
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=10)
        took = time.monotonic() - t0
    finally:
        if p.poll() is None:
            p.kill()
        os.close(master)
        os.close(slave)
    assert took < 1.0, f"SIGTERM took {took:.2f} s"
    assert p.returncode == 0, err                  # the loop itself stopped, not the guard
    assert "link" in json.loads(out)["fault_names"]


STUCK = """
import sys, time
import device.pi.__main__ as m

class Stuck:                       # a loop caught in a call that never returns
    stopped = False
    def run(self):
        print("running", flush=True)
        while True:
            time.sleep(0.01)

m.build_runtime = lambda *a, **k: Stuck()
sys.exit(m.main(["run", "--camera", "sim://walk", "--imu", "none", "--serial", "loop://"]))
"""


def test_sigterm_ends_even_a_stuck_loop_within_1_s():
    import signal
    p = subprocess.Popen([sys.executable, "-c", STUCK], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "running"
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=10)
        took = time.monotonic() - t0
    finally:
        if p.poll() is None:
            p.kill()
    assert took < 1.0 and p.returncode == 3
    assert "still running 0.8 s after SIGTERM" in err


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full")
def test_a_full_disk_under_json_log_is_a_warning_and_a_count_not_an_exit(tmp_path, capsys):
    status = tmp_path / "st.json"
    rc, err = _run_main(["--camera", "sim://press-hard", "--json-log", "/dev/full",
                         "--status", str(status), "--frames", "6"], capsys)
    assert rc == 0, err
    assert "Traceback" not in err
    assert err.count("--json-log /dev/full: cannot write") == 1       # warned once
    doc = json.loads(status.read_text())
    assert doc["frames"] == 6 and doc["json_log_lines_lost"] == 6


def test_status_naming_a_folder_refuses_to_start(tmp_path, capsys):
    rc, err = _run_main(["--camera", "sim://press-hard", "--status", str(tmp_path)], capsys)
    assert rc == 2
    line, = err.strip().splitlines()
    assert f"--status {str(tmp_path)!r} is a folder" in line


def test_mcap_without_the_viz_extra_is_one_line_naming_it_and_exit_2(monkeypatch, capsys,
                                                                     tmp_path):
    monkeypatch.setitem(sys.modules, "mcap", None)        # import mcap fails
    rc, err = _run_main(["--camera", "sim://press-hard", "--mcap", str(tmp_path / "r.mcap")],
                        capsys)
    assert rc == 2
    line, = err.strip().splitlines()
    assert "pip install .[viz]" in line and "--mcap" in line
    assert not (tmp_path / "r.mcap").exists()


def test_mcap_in_a_missing_folder_or_a_bad_size_refuses_to_start(tmp_path, capsys):
    pytest.importorskip("mcap")
    rc, err = _run_main(["--camera", "sim://press-hard", "--mcap",
                         str(tmp_path / "nope" / "r.mcap")], capsys)
    assert rc == 2 and "nope" in err and "does not exist" in err
    rc, err = _run_main(["--camera", "sim://press-hard", "--mcap", str(tmp_path / "r.mcap"),
                         "--mcap-max-mb", "0"], capsys)
    assert rc == 2 and "--mcap-max-mb" in err


def test_the_runtime_imports_without_mcap():
    code = ("import sys; sys.modules['mcap'] = None\n"
            "import device.pi.__main__, device.pi.runtime.loop, device.pi.runtime.mcaplog\n"
            "print('ok')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_foxglove_without_the_viz_extra_or_with_a_bad_port_refuses_to_start(monkeypatch,
                                                                           capsys):
    rc, err = _run_main(["--camera", "sim://press-hard", "--foxglove", "host:99999"], capsys)
    assert rc == 2 and "'host:99999'" in err and "[HOST:]PORT" in err
    monkeypatch.setitem(sys.modules, "foxglove", None)    # import foxglove fails
    rc, err = _run_main(["--camera", "sim://press-hard", "--foxglove", "8765"], capsys)
    line, = err.strip().splitlines()
    assert rc == 2 and "--foxglove" in line and "pip install .[viz]" in line


def test_the_runtime_says_which_profile_it_runs(tmp_path, capsys):
    """Its last line, its JSON summary and its status file name the profile it runs
    (name, where it came from, pins): the default roboskin, and a calibrated .toml
    the leg config names (issue 33)."""
    from device.sim import Simulator, load_scene
    from host.analysis.calibrate import calibrate, write_profile
    base = ["run", "--imu", "none", "--serial", "loop://", "--frames", "2", "--rules-only",
            "--camera", "sim://no-touch"]
    st = tmp_path / "st.json"
    assert main(base + ["--status", str(st)]) == 0
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.endswith("; profile roboskin (roboskin, 133 pins)"), last
    assert json.loads(st.read_text())["profile"] == {"name": "roboskin", "source": "roboskin",
                                                     "pins": 133}
    sim = Simulator(load_scene("no-touch"), seed=0)
    prof = write_profile(calibrate([sim.render(i) for i in range(6)], name="mine"),
                         tmp_path / "mine.toml")
    cfg = tmp_path / "leg.toml"
    cfg.write_text(f'[models]\nprofile = "{prof}"\n')
    assert main(base + ["--config", str(cfg), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)["profile"]
    assert got["name"] == "mine" and got["source"] == str(prof) and abs(got["pins"] - 133) <= 3
    assert main(base + ["--config", str(cfg)]) == 0
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.endswith(f"; profile mine ({prof}, {got['pins']} pins)"), last


# --- one catch for tacfoot's errors, and -v/-q (issues 31 and 32) ------------------

def test_quiet_leaves_errors_only_verbose_adds_debug_and_json_stays_on_stdout(capsys):
    base = ["--camera", "sim://walk", "--json"]
    assert _run_main(base, capsys) == (0, "")          # --json: the summary is on stdout
    rc = main(["run", "--imu", "none", "--serial", "loop://", "--frames", "2",
               "--camera", "sim://walk"])
    out, err = capsys.readouterr()
    assert rc == 0 and out == "" and err.startswith("device.pi run: 2 frames, ")
    rc = main(["run", "-q", "--imu", "none", "--serial", "loop://", "--frames", "2",
               "--camera", "sim://walk"])
    assert rc == 0 and capsys.readouterr() == ("", "")
    rc = main(["-v", "run", "--imu", "none", "--serial", "loop://", "--frames", "2",
               "--camera", "sim://walk", "--json"])
    out, err = capsys.readouterr()
    assert rc == 0 and json.loads(out)["frames"] == 2
    assert err.startswith("device.pi run: camera sim://walk, IMU none, ")
    rc, err = _run_main(["-q", "--camera", "sim://nope"], capsys)
    assert rc == 2 and err.count("\n") == 1 and "device.pi run: error: --camera" in err


def test_a_plain_bug_in_the_runtime_is_not_reported_as_bad_input(monkeypatch, capsys):
    import device.pi.__main__ as entry

    def broken(*a, **kw):
        raise KeyError("fps")
    monkeypatch.setattr(entry, "build_runtime", broken)
    with pytest.raises(KeyError):
        _run_main(["--camera", "sim://walk"], capsys)
