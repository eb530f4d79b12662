"""The command line end to end, as a user runs it: the real console script in real processes, or its main function
in this process (the ``cli`` fixture) where a test is about what a command does rather than the process it runs in."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers.camera import FakeCamera
from tests_paths import ROOT, tiny

pytestmark = pytest.mark.timeout(300)


def command(*args: str) -> list[str]:
    exe = shutil.which("vpengine", path=str(ROOT / ".venv" / "bin")) or shutil.which("vpengine")
    return [exe, *args] if exe else [sys.executable, "-m", "vpengine.cli.main", *args]


def vpengine(*args: str, timeout: float = 240, cwd=ROOT) -> subprocess.CompletedProcess:
    return subprocess.run(command(*args), capture_output=True, text=True, timeout=timeout, cwd=cwd)


def test_run_on_the_street_video_writes_every_heads_outputs_and_a_summary(tmp_path):
    # the shipped street video by its path: the first 5 s (50 frames) of OpenCV's 795-frame vtest.avi, 768x576 at
    # 10 fps, run to its end like the whole file, in a fraction of the time
    from vpengine.io.sources import sample

    video = sample("street")
    assert video.exists(), f"sample missing: {video}"
    out = tmp_path / "out"
    p = vpengine(
        "run",
        "-c",
        "configs/tiny.yaml",
        "-s",
        str(video),
        "-o",
        str(out),
        "--save-every",
        "20",
        "--viz",
        "--no-progress",
    )
    assert p.returncode == 0, p.stderr
    assert "50 frames" in p.stdout and "lockstep" in p.stdout
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_submitted"] == 50 and s["pace"] == "lockstep"
    for name in ("foundation", "depth", "seg", "det"):
        m = s["models"][name]
        assert m["runs"] == 50 and m["skipped"] == 0 and m["errors"] == 0, (name, m)
    for head in ("depth", "seg", "det"):
        e2e = s["models"][head]["e2e_latency_ms"]
        assert 0 < e2e["p50"] <= e2e["p99"]
    from vpengine.io.sinks import load_depth

    depth = load_depth(out / "depth", "000020")  # a 16-bit PNG and its scale (Note [Depth PNG])
    assert depth.shape == (576, 768) and depth.dtype == np.float32 and np.isfinite(depth).all()
    np.testing.assert_array_equal(load_depth(out / "depth", 20), depth)  # a video frame's number names it too
    with pytest.raises(KeyError, match=r"no depth of frame '000021' in .* \(3 frames: '000000', '000020', '000040'\)"):
        load_depth(out / "depth", 21)
    assert sorted(p.name for p in (out / "depth").glob("*.png")) == [f"{i:06d}.png" for i in (0, 20, 40)]
    assert not s["interrupted"] and s["inputs_skipped"] == []
    import cv2

    seg = cv2.imread(str(out / "seg" / "000040.png"), cv2.IMREAD_UNCHANGED)
    assert seg.shape == (576, 768) and seg.dtype == np.uint8
    lines = (out / "det" / "detections.jsonl").read_text().splitlines()
    assert [json.loads(x)["frame_id"] for x in lines] == list(range(50))  # one line per frame, in order
    first = json.loads(lines[0])
    assert len(first["boxes"]) == len(first["scores"]) == len(first["names"])
    assert (out / "depth" / "viz" / "000000.jpg").exists() and (out / "det" / "viz" / "000000.jpg").exists()


def test_run_with_the_synthetic_source_needs_no_files(tmp_path, cli):
    p = cli(
        "run",
        "-c",
        "configs/tiny.yaml",
        "-s",
        "synthetic:320x240@30:60",
        "--no-progress",
        "--set",
        "heads.seg.rate_hz=10",
        "--mode",
        "thread",
        "-o",
        str(tmp_path),
    )
    assert p.returncode == 0, p.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["pace"] == "realtime" and s["frames_submitted"] == 60 and s["mode"] == "thread"
    seg = s["models"]["seg"]
    # 2 s of frames at 10 Hz: 20 runs on an idle machine; a loaded one that falls behind the camera's pace takes
    # longer and runs seg more often, yet never above 10 Hz of the run's own time (+-1 and the drain)
    assert seg["target_hz"] == 10 and 10 <= seg["runs"] <= 10 * s["wall_s"] + 2, (seg, s["wall_s"])
    fm = s["models"]["foundation"]
    assert fm["runs"] + fm["skipped"] == 60
    # the config as it ran, overrides applied, loads again as a config
    from vpengine.config import load_config

    used = load_config(s["config_used"])
    assert used.head("seg").rate_hz == 10 and used.mode == "thread" and used.name == s["config"]
    # a live source never waits for the writer (Note [Sink thread]); a result it could not write is counted
    depth = s["models"]["depth"]
    written = len(list((tmp_path / "depth").glob("*.png")))
    assert written > 0 and written + depth["results_unwritten"] == depth["results_received"]


def test_a_realtime_run_waits_for_a_slow_heads_frames_in_flight_at_the_end(tmp_path, cli):
    """Note [The frames in flight at the end]: a head slower than the end's poll of the results (here 0.6 s a frame)
    still answers every frame it took, and the summary counts it; it used to be left behind with 0 runs."""
    opts = json.dumps({"sleep_ms": 600})
    p = cli(
        "run", "-c", "configs/tiny.yaml", "-s", "synthetic:160x120@30:3", "--no-progress", "--mode", "thread",
        "--set", "heads.seg.model=helpers.faulty:FaultyHead", "--set", f"heads.seg.options={opts}",
        "-o", str(tmp_path),
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    fm, seg = s["models"]["foundation"], s["models"]["seg"]
    assert fm["runs"] + fm["skipped"] == 3 and fm["runs"] >= 1
    assert seg["runs"] >= 1 and seg["runs"] + seg["skipped"] + seg["dropped"] == fm["runs"], (fm, seg)
    assert seg["results_received"] == seg["runs"]


def test_the_end_of_a_realtime_run_waits_a_bounded_time_and_names_the_heads_it_leaves(cli, monkeypatch, caplog):
    """Note [The frames in flight at the end]: a head slower than END_WAIT_S is left with a warning naming it."""
    import logging

    from vpengine.pipeline import run as pipeline_run

    monkeypatch.setattr(pipeline_run, "END_WAIT_S", 0.2)
    opts = json.dumps({"sleep_ms": 2500})
    with caplog.at_level(logging.WARNING, "vpengine.run"):
        p = cli("run", "-c", "configs/tiny.yaml", "-s", "synthetic:160x120@30:2", "--no-progress", "--mode", "thread",
                "--set", "heads.seg.model=helpers.faulty:FaultyHead", "--set", f"heads.seg.options={opts}")  # fmt: skip
    assert p.returncode == 0, p.stderr
    said = [m for m in caplog.messages if m.startswith("stopped waiting for the frames in flight after 0 s: ")]
    assert len(said) == 1 and "no output from ['seg']" in said[0], caplog.messages


def test_a_head_whose_kind_lacks_its_outputs_is_written_as_a_generic_heads(tmp_path, cli, caplog):
    """Note [Kinds and outputs]: a segmentation head whose map is named mask (not classes) crashed the run's writer
    (KeyError 'classes', no summary.json); its outputs are written as .npz and planning says why."""
    import logging

    with caplog.at_level(logging.WARNING, "vpengine.plan"):
        p = cli("run", "-c", "tiny", "-s", "synthetic:160x120@30:3", "--no-progress", "--mode", "thread",
                "--set", "heads.seg.model=helpers.models:MaskSegHead", "-o", str(tmp_path))  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "summary.json").is_file() and len(list((tmp_path / "seg").glob("*.npz"))) == 3
    assert any("seg: meta['kind'] is 'segmentation'" in m and "['mask']" in m for m in caplog.messages)


def test_a_config_for_float_frames_runs_on_files_whose_frames_are_uint8(tmp_path, cli):
    """input.dtype (and input.color) say how the API's callers hand frames in; the CLI's sources give uint8 BGR (or
    RGB) frames whatever the config says, and the run takes them as they are."""
    p = cli("run", "-c", "tiny", "-s", "synthetic:160x120@30:3", "--no-progress", "--mode", "thread",
            "--set", "input.dtype=float32", "-o", str(tmp_path))  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert json.loads((tmp_path / "summary.json").read_text())["frames_submitted"] == 3


def test_a_models_row_over_several_cameras_sums_its_lanes_targets_as_it_sums_their_rates(cli):
    p = cli("run", "-c", "tiny", "-s", "front=synthetic:160x120@30:3", "-s", "rear=synthetic:160x120@30:3",
            "--no-progress", "--mode", "thread", "--set", "heads.depth.rate_hz=5")  # fmt: skip
    assert p.returncode == 0, p.stderr
    rows = {ln.split()[0]: ln.split()[1] for ln in p.stdout.splitlines() if ln.startswith(("depth", "seg"))}
    assert rows["depth@front"] == rows["depth@rear"] == "5" and rows["depth"] == "10", p.stdout
    assert rows["seg"] == "max"


def test_a_camera_faster_than_the_loop_gives_its_newest_frames_and_every_frame_is_submitted_or_counted(
    tmp_path,
):
    """Note [Live capture]: a camera is read on its own thread; the loop takes the newest frame, never a stale one
    from the driver's queue, and the ones it never took are in the summary."""
    from vpengine.cli.run import format_summary
    from vpengine.io.sources import VideoSource
    from vpengine.pipeline.run import run_pipeline

    cam = FakeCamera(end_at=150, width=160, height=120)
    source = VideoSource(0, capture=cam)
    cam.stream(fps=300)  # faster than 2 CPU cores run three heads: frames pile up unless the newest is taken
    # lockstep: every frame taken runs through every head and is written, so the files show what was taken
    s = run_pipeline(tiny("thread"), source, tmp_path / "o", pace="lockstep", progress=False)
    assert s["frames_submitted"] + s["source_missed"] == 150 and s["source_missed"] > 0
    assert f"camera frames a newer one replaced: {s['source_missed']}" in format_summary(s)
    names = [int(p.stem) for p in sorted((tmp_path / "o" / "depth").glob("*.png"))]
    assert len(names) == s["frames_submitted"] and names[-1] == 149  # gaps where frames were replaced


def test_image_folder_source(tmp_path, cli, caplog):
    import cv2

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(5):
        cv2.imwrite(str(frames / f"im{i}.png"), np.full((60, 80, 3), i * 40, np.uint8))
    out = tmp_path / "o"
    # a head paused from the start: lockstep waits for the others only
    p = cli(
        "run",
        "-c",
        "configs/tiny.yaml",
        "-s",
        str(frames),
        "-o",
        str(out),
        "--no-progress",
        "--set",
        "heads.seg.rate_hz=0",
    )
    assert p.returncode == 0, p.stderr
    assert sorted(x.name for x in (out / "depth").glob("*.png")) == [f"im{i}.png" for i in range(5)]
    s = json.loads((out / "summary.json").read_text())
    assert s["models"]["seg"]["runs"] == 0 and s["models"]["depth"]["results_received"] == 5
    assert "no output from" not in p.stderr + caplog.text  # never waited for the paused head (a logged warning)


def test_config_errors_are_reported_without_a_traceback(tmp_path, cli):
    bad = tmp_path / "bad.yaml"
    bad.write_text("heads:\n  - {name: d, model: tiny_depth, rate: 5}\n")
    p = cli("run", "-c", str(bad), "-s", "synthetic:64x64@30:3")
    assert p.returncode == 1
    assert "heads.d.rate: unknown key" in p.stderr and "Traceback" not in p.stderr
    p = cli("run", "-c", "configs/tiny.yaml", "-s", str(tmp_path / "missing.avi"))
    assert p.returncode == 1 and "does not exist" in p.stderr


def test_info_reports_versions_devices_and_mps():
    p = vpengine("info", "--json")
    assert p.returncode == 0, p.stderr
    info = json.loads(p.stdout)
    assert info["versions"]["vpengine"] and info["versions"]["torch"]
    assert info["devices"][0]["device"] == "cpu"
    assert "reachable" in info["mps"] and "pipe_directory" in info["mps"]


# ------------------------------------------------------------------------------------------------ predict, configs
def test_predict_writes_annotated_pictures_to_a_new_folder_each_time_from_any_directory(tmp_path, cli):
    """No config file, no media: the default config and the sample ship with the package."""
    import cv2

    p = vpengine("predict", "sample:cheetah", "--no-progress", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "rate limits off: every head runs on every frame" in p.stdout
    assert "annotated pictures and summary.json in runs/predict\n" in p.stdout
    picture = cv2.imread(str(tmp_path / "runs" / "predict" / "cheetah.jpg"))
    assert picture.shape == (1080, 1920, 3)  # input, depth, seg, det: 2 x 2 pictures of 540 x 960
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        cv2.imwrite(str(frames / f"im{i}.jpg"), np.full((120, 160, 3), 60 * i, np.uint8))
    # a second run never writes into the first one's folder; the config's rate limits are off, and it says so
    p = cli(
        "predict", str(frames / "*.jpg"), "-c", "tiny", "--set", "heads.seg.rate_hz=1", "--mode", "thread",
        "--no-progress", cwd=tmp_path,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "(the config limits seg to 1 Hz)" in p.stdout and "in runs/predict2\n" in p.stdout
    assert sorted(x.name for x in (tmp_path / "runs" / "predict2").iterdir()) == [
        "im0.jpg", "im1.jpg", "im2.jpg", "summary.json",
    ]  # fmt: skip
    s = json.loads((tmp_path / "runs" / "predict2" / "summary.json").read_text())
    assert all(s["models"][h]["runs"] == 3 for h in ("depth", "seg", "det"))
    assert sorted(x.name for x in (tmp_path / "runs" / "predict").iterdir()) == [
        "cheetah.jpg",
        "summary.json",
    ]


def test_configs_are_found_by_name_listed_and_shown_from_any_directory(tmp_path, monkeypatch, capsys, cli):
    p = vpengine("config", "list", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    listed = dict(line.split(None, 1) for line in p.stdout.splitlines())
    assert set(listed) >= {"tiny", "dinov2s_depth_seg_det", "tiny_every_frame"}
    assert listed["tiny"].startswith("Tiny random-weight models")
    p = cli("config", "show", "tiny", cwd=tmp_path)
    assert p.returncode == 0 and "name: tiny" in p.stdout and "model: tiny_vit" in p.stdout
    (tmp_path / "bad.yaml").write_text("# mine\nmode: proces\n")
    p = cli("config", "show", str(tmp_path / "bad.yaml"), cwd=tmp_path)
    assert p.returncode == 1 and "# mine\nmode: proces" in p.stdout  # shown as written, and said not to load
    assert "vpengine config show: error: invalid configuration in" in p.stderr and "mode: Input should be" in p.stderr
    monkeypatch.chdir(tmp_path)  # the rest in this process: nothing here starts an engine
    from vpengine import configs
    from vpengine.cli.main import main

    shipped = ROOT / "src" / "vpengine" / "configs"
    assert configs.resolve("tiny") == configs.resolve("tiny.yaml") == shipped / "tiny.yaml"
    (tmp_path / "tiny.yaml").write_text("name: mine\n")
    assert configs.resolve("tiny.yaml") == Path("tiny.yaml")  # a file that exists is always taken as it is
    assert main(["run", "-c", "nope", "-s", "synthetic:64x64@30:3"]) == 1
    err = capsys.readouterr().err
    assert "config 'nope' is neither a file nor a shipped config; shipped (by name, e.g. -c tiny): " in err
    assert "dinov2s_depth_seg_det" in err and "Traceback" not in err
    assert main(["run", "-c", "configs/tiny.yaml", "-s", "synthetic:64x64@30:3"]) == 1  # a path is never a name
    assert "config 'configs/tiny.yaml' is neither a file nor a shipped config" in capsys.readouterr().err


def test_the_package_installs_its_configs_and_samples(tmp_path):
    """Package data must name files that exist: a wheel built from the tree carries every config and sample."""
    import zipfile

    tree = tmp_path / "tree"
    tree.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, tree / name)
    shutil.copytree(ROOT / "src", tree / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    p = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path), str(tree)],
        capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    (wheel,) = tmp_path.glob("vpengine-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    configs = {f"vpengine/configs/{p.name}" for p in (ROOT / "src" / "vpengine" / "configs").glob("*.yaml")}
    assert "vpengine/configs/tiny.yaml" in configs and configs <= names
    assert {
        "vpengine/samples/street.mp4",
        "vpengine/samples/cheetah.jpg",
        "vpengine/samples/README.md",
    } <= names


# ------------------------------------------------------------------------------------------------ runs to live with
def test_run_writes_an_annotated_video_of_the_shipped_street_sample(tmp_path, cli):
    import cv2

    p = cli(
        "run", "-c", "tiny", "-s", "sample:street", "--max-frames", "12", "--video", str(tmp_path / "v.mp4"),
        "--mode", "thread", "--no-progress",
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert f"annotated video in {tmp_path / 'v.mp4'}" in p.stdout
    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == 12 and cap.get(cv2.CAP_PROP_FPS) == 10  # the video's rate
    assert (cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (1536, 1152)  # 2 x 2
    cap.release()


@pytest.mark.parametrize("cmd", ["run", "lockstep", "predict"])
def test_ctrl_c_ends_the_run_with_its_summary(tmp_path, cmd):
    import signal
    import time

    out = tmp_path / "out"
    source = "synthetic:160x120@30:100000"
    args = ["run", "-c", "tiny", "-s", source] if cmd != "predict" else ["predict", source]
    if cmd == "lockstep":  # frames read ahead on a thread of their own (Note [Read ahead])
        args += ["--pace", "lockstep"]
    if cmd != "run":  # process mode's workers once (run), thread mode's quicker start for the other two
        args += ["--mode", "thread"]
    proc = subprocess.Popen(
        command(*args, "-o", str(out), "--no-progress"), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        first = out / "depth" if cmd != "predict" else out
        deadline = time.monotonic() + 120
        while not (first.is_dir() and any(first.glob("0*"))):  # frames are going through
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "stopping after this frame" in stderr
    assert "interrupted after " in stdout and "foundation" in stdout  # the summary table
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"] and 0 < s["frames_submitted"] < 100000
    if cmd == "lockstep":  # every frame that went in was answered by every head and written, nothing more
        n = s["frames_submitted"]
        assert len(list((out / "depth").glob("*.png"))) == len(list((out / "seg").glob("*.png"))) == n
        assert len((out / "det" / "detections.jsonl").read_text().splitlines()) == n


def test_outputs_and_arguments_are_checked_before_the_engine_starts(tmp_path, capsys, monkeypatch, cli):
    """In the CLI's own process, with an engine that must not be made: every check comes first."""
    from vpengine.cli.main import main

    def no_engine(*args, **kwargs):
        raise AssertionError("the engine was made before the outputs were checked")

    monkeypatch.setattr("vpengine.engine.Engine.__init__", no_engine)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "old.png").write_bytes(b"")
    (tmp_path / "file").write_text("")
    (tmp_path / "v.mp4").write_bytes(b"")
    (tmp_path / "bag").mkdir()
    run = ["run", "-c", "tiny", "-s", "synthetic:64x64@30:3", "--no-progress"]
    for args, message in [
        (
            ["-o", str(tmp_path / "full")],
            "exists already and holds files; give a new folder, or add --exist-ok",
        ),
        (["-o", str(tmp_path / "file" / "out")], f"cannot write --out '{tmp_path / 'file' / 'out'}': "),
        (
            ["--video", str(tmp_path / "v.mp4")],
            "exists already; give a new name, or add --exist-ok to replace it",
        ),
        (["--out-bag", str(tmp_path / "bag")], "exists already; give a new name (never overwritten)"),
        (
            ["--out-bag", str(tmp_path / "run.mcap")],
            f"--out-bag '{tmp_path / 'run.mcap'}': a rosbag2 bag is a folder that holds its mcap file; give the "
            f"folder's name: '{tmp_path / 'run'}' writes {tmp_path / 'run' / 'run'}.mcap",
        ),
        (
            ["--out-bag", str(tmp_path / "run.db3"), "--bag-storage", "sqlite3"],
            f"give the folder's name: '{tmp_path / 'run'}' writes {tmp_path / 'run' / 'run'}.db3",
        ),
        (
            ["--video", str(tmp_path / "v.gif")],
            f"--video '{tmp_path / 'v.gif'}': cannot write a video as '.gif'; name it .mp4, .avi, .m4v, .mkv, .mov, "
            ".webm",
        ),
        (["-s", "synthetic:64x64@30:3"], "2 sources without camera names ('synthetic:64x64@30:3', "),
    ]:
        assert main([*run, *args]) == 1
        err = capsys.readouterr().err
        assert err.startswith("vpengine run: error: ") and message in err and err.count("\n") == 1, err
    assert main(["run", "-c", "tiny", "-s", "synthetic:64x64@0", "--no-progress"]) == 1
    assert "synthetic source rate must be a number of Hz above 0, got 0.0" in capsys.readouterr().err
    assert not (tmp_path / "full" / "summary.json").exists()
    for option, value in [("--max-frames", "-1"), ("--max-frames", "0"), ("--fps", "0"), ("--fps", "-5"),
                          ("--fps", "nan"), ("--fps", "inf"), ("--save-every", "0")]:  # fmt: skip
        with pytest.raises(SystemExit) as e:
            main([*run, option, value])
        err = capsys.readouterr().err
        assert e.value.code == 2 and f"argument {option}: expected " in err, (option, value, err)
    monkeypatch.undo()
    p = cli(*run, "-o", str(tmp_path / "full"), "--exist-ok", "--mode", "thread")
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "full" / "summary.json").exists() and (tmp_path / "full" / "old.png").exists()


def test_a_missing_optional_extra_says_what_to_install(tmp_path):
    bag = tmp_path / "in.mcap"
    bag.write_bytes(b"")
    # one interpreter for both commands: each answers and the next one runs, with its exit code after its message
    script = (
        "import json, sys; sys.modules['rosbags'] = None; sys.modules['cyclonedds'] = None\n"
        "from vpengine.cli.main import main\n"
        "for args in json.loads(sys.argv[1]):\n"
        "    print(f'exit {main(args)}', file=sys.stderr)"
    )
    runs = [["run", "-c", "tiny", "-s", str(bag)], ["ros2", "-c", "tiny", "--input-topic", "/cam"]]
    p = subprocess.run([sys.executable, "-c", script, json.dumps(runs)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "Traceback" not in p.stderr, p.stderr
    lines = p.stderr.strip().splitlines()
    ends = [i for i, line in enumerate(lines) if line.startswith("exit ")]
    assert [lines[i] for i in ends] == ["exit 1", "exit 1"], p.stderr
    for i, missing in zip(ends, ("rosbags", "cyclonedds")):
        assert lines[i - 1].endswith(
            f"needs the optional extra 'ros2' ({missing} is not installed): pip install 'vpengine[ros2]'"
        ), p.stderr


def test_an_unreadable_image_is_skipped_and_listed_in_the_summary(tmp_path, cli):
    import cv2

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(4):
        cv2.imwrite(str(frames / f"im{i}.png"), np.full((120, 160, 3), 50 * i, np.uint8))
    (frames / "im2.png").write_bytes(b"not an image")
    p = cli("run", "-c", "tiny", "-s", str(frames), "-o", str(tmp_path / "o"), "--mode", "thread", "--no-progress")
    assert p.returncode == 0, p.stderr
    assert "images skipped as unreadable: 1 (listed in summary.json)" in p.stdout
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["frames_submitted"] == 3 and s["inputs_skipped"] == [
        {"file": str(frames / "im2.png"), "why": "not a readable image"}
    ]


def test_a_video_cut_short_is_counted_and_listed_in_the_summary(tmp_path, cli):
    import cv2

    w = cv2.VideoWriter(str(tmp_path / "whole.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    rng = np.random.default_rng(0)
    for _ in range(20):
        w.write(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    w.release()
    data = (tmp_path / "whole.avi").read_bytes()
    (tmp_path / "cut.avi").write_bytes(data[: len(data) // 2])  # its header still announces 20 frames
    p = cli("run", "-c", "tiny", "-s", str(tmp_path / "cut.avi"), "-o", str(tmp_path / "o"), "--mode", "thread",
            "--no-progress")  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "inputs truncated, decoded partially: 1 (listed in summary.json)" in p.stdout
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert 0 < s["frames_submitted"] < 18 and s["inputs_partial"] == [str(tmp_path / "cut.avi")]


def test_a_folder_of_mixed_sizes_gives_outputs_at_each_images_size(tmp_path, cli):
    import cv2

    from vpengine.io.sinks import load_depth

    frames = tmp_path / "frames"
    frames.mkdir()
    sizes = [(120, 160), (90, 200), (300, 140)]
    for i, (h, w) in enumerate(sizes):
        cv2.imwrite(str(frames / f"im{i}.png"), np.full((h, w, 3), 70 * i, np.uint8))
    p = cli("predict", str(frames), "-o", str(tmp_path / "p"), "--mode", "thread", "--no-progress")
    assert p.returncode == 0, p.stderr
    p = cli("run", "-c", "tiny", "-s", str(frames), "-o", str(tmp_path / "o"), "--mode", "thread", "--no-progress")
    assert p.returncode == 0, p.stderr
    for i, size in enumerate(sizes):
        assert load_depth(tmp_path / "o" / "depth", f"im{i}").shape == size
        assert cv2.imread(str(tmp_path / "o" / "seg" / f"im{i}.png"), cv2.IMREAD_UNCHANGED).shape == size


def test_a_run_with_frames_a_head_failed_on_ends_with_exit_status_3_naming_them(tmp_path, cli):
    # every frame answered, the errors counted: the run goes to its end, and its exit status says so
    p = cli(
        "run", "-c", "tiny", "-s", "synthetic:64x64@30:8", "-o", str(tmp_path / "o"), "--mode", "thread", "--no-progress",
        "--set", "heads.seg.model=helpers.faulty:FaultyHead", "--set", "heads.seg.options={raise_every: 2}",
    )  # fmt: skip
    assert p.returncode == 3, p.stderr
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    failed = s["models"]["seg"]["errors"]
    assert failed >= 3 and s["models"]["depth"]["errors"] == 0 and s["frames_submitted"] == 8
    assert f"vpengine run: frames a model failed on: seg {failed} (counted in summary.json" in p.stderr
    p = cli("run", "-c", "tiny", "-s", "synthetic:64x64@30:3", "--mode", "thread", "--no-progress")
    assert p.returncode == 0, p.stderr
