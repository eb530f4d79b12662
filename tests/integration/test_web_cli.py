"""``--serve`` on the commands that run an engine, as a user runs them (real console script, real HTTP)."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request

import pytest

from tests_paths import ROOT

pytestmark = pytest.mark.timeout(300)


def start(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    exe = shutil.which("vpengine", path=str(ROOT / ".venv" / "bin")) or shutil.which("vpengine")
    cmd = [exe, *args] if exe else [sys.executable, "-m", "vpengine.cli.main", *args]
    return subprocess.Popen(
        cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})}
    )


def view_url(proc: subprocess.Popen, timeout: float = 120) -> str:
    deadline = time.monotonic() + timeout
    seen = []
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        seen.append(line)
        if m := re.search(r"live view at (http://\S+)", line):
            return m.group(1)
    proc.kill()
    raise AssertionError("no 'live view at' line:\n" + "".join(seen) + proc.stderr.read())


def get(url: str, method: str = "GET", body: bytes | None = None, token: str | None = None):
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    req = urllib.request.Request(url, data=body, method=method, headers=headers)
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.headers, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers, e.read()


def eventually(check, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while not (got := check()):
        assert time.monotonic() < deadline, f"{what}: not within {timeout} s"
        time.sleep(0.1)
    return got


def test_run_serves_the_view_while_it_runs_and_rates_and_priorities_set_there_reach_the_engine():
    proc = start(
        "run", "-c", "configs/tiny.yaml", "-s", "synthetic:160x120@30:180", "--no-progress",
        "--set", "mode=thread", "--serve", "0",
    )  # fmt: skip
    try:
        url = view_url(proc)
        assert url.startswith("http://127.0.0.1:")  # loopback unless asked
        stats = json.loads(eventually(lambda: (s := get(url + "api/stats"))[0] == 200 and s[2], 60, "stats"))
        assert set(stats["models"]) == {"foundation", "depth", "seg", "det"}
        _status, headers, _ = eventually(
            lambda: (p := get(url + "api/latest/seg.jpg"))[0] == 200 and p, 30, "a seg picture"
        )
        assert headers["X-On-Frame"] == "1"  # drawn on its own input frame, which the run loop keeps
        assert get(url + "api/rate/seg", "PUT", b'{"hz": 4}')[0] == 200
        assert 'vpengine_target_hz{model="seg"} 4.0' in get(url + "metrics")[2].decode()
        status, _, reply = get(url + "api/priority/depth", "PUT", b'{"priority": 9}')
        assert status == 200 and json.loads(reply) == {"head": "depth", "camera": None, "priority": 9}
        models = json.loads(get(url + "api/stats")[2])["models"]
        assert (models["depth"]["priority"], models["seg"]["priority"]) == (9, 0)
        status, _, reply = get(url + "api/priority/foundation", "PUT", b'{"priority": 9}')
        assert status == 404 and "follows its heads'" in json.loads(reply)["error"]  # the engine's own reason
        status, _, reply = get(url + "api/priority/seg", "PUT", b'{"priority": 101}')
        assert status == 400 and "from -100 to 100" in json.loads(reply)["error"]
        assert json.loads(get(url + "api/stats")[2])["models"]["seg"]["priority"] == 0
        summary = summary_lines(proc)
        assert ended_line(proc) == url  # the run is over; its view stays (Note [Serving on])
        proc.send_signal(signal.SIGTERM)  # as a service manager ends it
        _out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 0, err
    seg = next(line for line in summary if line.startswith("seg "))
    assert seg.split()[1] == "4"  # the summary's target column
    with pytest.raises(OSError):  # the view ended with the process
        get(url + "api/stats")


def summary_lines(proc: subprocess.Popen) -> list[str]:
    """The summary the run prints on stdout, read up to its latency note."""
    lines = []
    while not lines or not lines[-1].startswith("(latency:"):
        line = proc.stdout.readline()
        assert line, "stdout ended before the summary:\n" + "".join(lines)
        lines.append(line)
    return lines


def ended_line(proc: subprocess.Popen) -> str:
    """The address in the line saying the run has ended and its view stays up."""
    seen = []
    while line := proc.stderr.readline():
        seen.append(line)
        if m := re.search(r"the run has ended; its live view stays at (http://\S+) until Ctrl-C", line):
            return m.group(1)
    raise AssertionError("no 'the run has ended' line:\n" + "".join(seen))


def test_the_view_of_a_finished_run_answers_until_ctrl_c(tmp_path):
    proc = start(
        "run", "-c", "tiny", "-s", "synthetic:160x120@30:6", "--pace", "lockstep", "--no-progress",
        "--set", "mode=thread", "--serve", "0", "-o", str(tmp_path / "run"),
    )  # fmt: skip
    try:
        url = view_url(proc)
        summary = summary_lines(proc)  # printed when the run ends, before the wait
        assert summary[0].startswith("6 frames in ")
        assert ended_line(proc) == url
        written = json.loads((tmp_path / "run" / "summary.json").read_text())
        assert written["frames_submitted"] == 6 and written["models"]["depth"]["runs"] == 6  # lockstep: every frame
        status, _, page = get(url)
        assert status == 200 and b"<html" in page.lower()
        status, _, body = get(url + "api/stats")
        assert status == 200 and json.loads(body)["models"]["depth"]["runs"] == 6  # the run's last state
        status, headers, jpeg = get(url + "api/latest/depth.jpg")
        assert status == 200 and jpeg.startswith(b"\xff\xd8") and headers["X-Frame-Id"] == "5"
        assert proc.poll() is None  # still up, however long that took
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 0, err
    assert "Traceback" not in err, err
    with pytest.raises(OSError):
        get(url + "api/stats")


def test_predict_serves_the_view_too_and_keeps_it_after_the_last_picture(tmp_path):
    proc = start(
        "predict", "synthetic:160x120@30:20", "-o", str(tmp_path / "pred"), "--no-progress", "--mode", "thread",
        "--serve", "0",
    )  # fmt: skip
    try:
        url = view_url(proc)
        stats = json.loads(eventually(lambda: (s := get(url + "api/stats"))[0] == 200 and s[2], 60, "stats"))
        assert set(stats["models"]) == {"foundation", "depth", "seg", "det"}
        summary = summary_lines(proc)  # printed when the run ends, before the wait
        assert any(line.startswith("20 frames in ") for line in summary), summary
        assert ended_line(proc) == url  # the run is over; its view stays (Note [Serving on])
        assert get(url + "api/latest/depth.jpg")[0] == 200
        assert len(list((tmp_path / "pred").glob("*.jpg"))) == 20
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 0, err


def test_serving_beyond_loopback_needs_a_token_and_then_every_request_carries_it(cli, monkeypatch):
    monkeypatch.delenv("VPENGINE_SERVE_TOKEN", raising=False)
    refused = cli("run", "-c", "configs/tiny.yaml", "-s", "synthetic:160x120@30:30", "--serve", "0.0.0.0:0")
    err = refused.stderr
    assert refused.returncode == 1 and "--serve-token" in err and "VPENGINE_SERVE_TOKEN" in err, err
    proc = start(
        "run", "-c", "configs/tiny.yaml", "-s", "synthetic:160x120@30:300", "--no-progress",
        "--set", "mode=thread", "--serve", "0.0.0.0:0", env={"VPENGINE_SERVE_TOKEN": "tok-123"},
    )  # fmt: skip
    try:
        url = view_url(proc)
        eventually(lambda: get(url + "api/stats", token="tok-123")[0] == 200, 60, "stats with the token")
        assert get(url + "api/stats")[0] == 401
        assert get(url + "api/rate/seg", "PUT", b'{"hz": 1}')[0] == 401
        assert get(url + "api/rate/seg", "PUT", b'{"hz": 1}', token="wrong")[0] == 401
        assert get(url + "?token=tok-123")[0] == 200
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=120)


@pytest.mark.xdist_group("dds")  # one DDS test at a time: no two share a domain or ports
def test_ros2_serves_the_view_with_pictures_on_the_messages_frames(monkeypatch):
    import numpy as np

    from vpengine.ros2 import cdr
    from vpengine.ros2 import dds_types as T
    from vpengine.ros2.dds import DdsContext, loopback_config
    from vpengine.ros2.messages import Header
    from vpengine.ros2.outputs import image_out

    domain = 20 + (os.getpid() * 7919 + int(time.time() * 1000)) % 200
    env = {"CYCLONEDDS_URI": loopback_config()}
    monkeypatch.setenv("CYCLONEDDS_URI", env["CYCLONEDDS_URI"])  # this process's participant too
    proc = start(
        "ros2", "-c", "configs/tiny.yaml", "--input-topic", "/web/camera", "--domain-id", str(domain),
        "--input-qos", "default", "--set", "mode=thread", "--serve", "127.0.0.1:0", env=env,
    )  # fmt: skip
    ctx = None
    try:
        url = view_url(proc)
        eventually(lambda: get(url + "api/stats")[0] == 200, 60, "stats")
        assert get(url + "api/latest/det.jpg")[0] == 204  # no message yet: no result
        ctx = DdsContext(domain)
        writer = ctx.writer("/web/camera", T.Image_, "default")
        eventually(lambda: writer.matched() >= 1, 30, "the bridge's reader matched")
        img = np.zeros((120, 160, 3), np.uint8)
        img[:, 80:] = 200
        for i in range(5):
            writer.write_raw(cdr.encode_image(image_out(img, "bgr8", Header(100 + i, 0, "cam"))))
            time.sleep(0.1)
        _status, headers, _ = eventually(
            lambda: (p := get(url + "api/latest/det.jpg"))[0] == 200 and p, 30, "a det picture"
        )
        assert headers["X-On-Frame"] == "1"
    finally:
        if ctx is not None:
            ctx.close()
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err


@pytest.fixture(scope="module")
def resource_tracker():
    """multiprocessing's resource tracker, started before the leak check looks (a module's fixture is set up before
    the autouse ``no_leaks``): a spawned process's queue or event starts this helper process, which then lives as
    long as this one; it is not a process the test left behind."""
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()


def test_bench_web_measures_the_stream_with_and_without_a_viewer(tmp_path, cli, resource_tracker):
    done = cli(
        "bench", "web", "--seconds", "1", "--rounds", "1", "--mode", "thread", "--name", "smoke",
        "--out", str(tmp_path),
    )  # fmt: skip
    out, err = done.stdout, done.stderr
    assert done.returncode == 0, err[-3000:]
    res = json.loads((tmp_path / "smoke.json").read_text())
    assert res["mode"] == "thread" and res["heads"] == ["depth", "seg", "det"] and res["fps"] == 30.0
    off, on = res["phases"]
    assert (off["viewer"], on["viewer"]) == (False, True)
    for phase in (off, on):
        assert phase["frames"] == 30 and phase["frame_latency_ms"]["n"] >= 25  # 1 s at 30 Hz, nearly all complete
        assert 0 < phase["frame_latency_ms"]["p50"] <= phase["frame_latency_ms"]["p99"]
    assert off["pictures_made"] == 0 and "viewer_requests" not in off  # nobody looking: nothing drawn
    asked = on["viewer_requests"]
    assert asked["errors"] == 0 and asked["stats"]["n"] >= 3 and asked["picture"]["n"] >= 6
    assert 0 < on["pictures_made"] <= asked["picture"]["n"]
    assert set(res["summary"]["overhead"]) >= {"frame_p50_ms", "frame_p99_ms", "engine_cpu_pct_of_one_core"}
    assert "viewer on vs off" in out
