"""Note [Heads at run time]: heads added and removed while the engine serves frames, in both modes; what they leave
behind over many cycles; bad requests refused with the engine as it was."""

from __future__ import annotations

import gc
import json
import os
import sys
import threading
import time
import urllib.error
import urllib.request

import pytest

from helpers import faulty
from helpers.builds import full_collections_can_be_held_off, held_elsewhere
from helpers.frames import frame
from helpers.groups import INDUCTOR
from helpers.waiting import wait_for
from tests_paths import tiny
from vpengine.bench.common import proc_stat
from vpengine.config import ConfigError
from vpengine.engine import Engine, EngineDeadError, EngineStartError
from vpengine.models.build import build_lock

pytestmark = pytest.mark.timeout(300)

DET2 = {"name": "det2", "model": "tiny_det"}


def two_heads(mode, *overrides):
    return tiny(mode, "heads=[{name: depth, model: tiny_depth}, {name: seg, model: tiny_seg}]", *overrides)


def descendants() -> set[int]:
    """Live processes descending from this one (workers are forked by a zygote this process started)."""
    parents: dict[int, int] = {}
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                parents[int(pid)] = int(proc_stat(f"/proc/{pid}/stat")[1])  # ppid
            except OSError:
                continue
    found, frontier = set(), {os.getpid()}
    while frontier:
        frontier = {p for p, pp in parents.items() if pp in frontier} - found
        found |= frontier
    return found


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_a_head_added_while_serving_answers_every_frame_after_it_and_the_others_never_miss_one(mode):
    with Engine(two_heads(mode)) as eng:
        imgs = [frame(i) for i in range(4)]
        added = threading.Event()
        errors = []

        def add():
            try:
                eng.add_head(DET2)
            except BaseException as e:
                errors.append(e)
            added.set()

        answered = []
        adder = threading.Thread(target=add)
        adder.start()
        deadline = time.monotonic() + 120
        while sum(after for after, _ in answered) < 5:
            after_add = added.is_set()
            out = eng.wait(eng.submit(imgs[len(answered) % 4]), timeout=30)
            answered.append((after_add, set(out)))
            assert time.monotonic() < deadline
        adder.join()
        assert not errors, errors
        assert all({"depth", "seg"} <= heads for _, heads in answered)  # no frame left out while det2 was built
        assert all("det2" in heads for after, heads in answered if after)
        assert [h.name for h in eng.config.heads] == ["depth", "seg", "det2"]
        assert eng.stats()["models"]["det2"]["runs"] >= 5
        assert eng.latest("det2") is not None
        assert eng.lanes.seats == ()  # the one spare seat is taken


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_removing_a_head_stops_its_worker_frees_its_mailbox_and_its_seat(mode):
    with Engine(two_heads(mode)) as eng:
        eng.add_head(DET2)
        eng.wait(eng.submit(frame(0)), timeout=30)
        procs = descendants()
        eng.remove_head("det2")
        assert "out.det2" not in eng.stats()["mailboxes"] and "det2" not in eng.stats()["models"]
        assert set(eng.wait(eng.submit(frame(1)), timeout=30)) == {"depth", "seg"}
        assert eng.lanes.seats == ("+0",)
        if mode == "process":
            assert len(procs - descendants()) == 1  # det2's worker is gone, nobody else
        eng.add_head({**DET2, "rate_hz": 5})  # the seat serves again, at its new rate
        assert eng.rate("det2") == 5
        time.sleep(0.3)  # a period of 5 Hz: the next frame is due
        assert set(eng.wait(eng.submit(frame(2)), timeout=30)) == {"depth", "seg", "det2"}
        eng.remove_head("seg")  # a head of the config goes too; it has no seat to give back
        time.sleep(0.3)
        assert eng.lanes.seats == () and set(eng.wait(eng.submit(frame(3)), timeout=30)) == {"depth", "det2"}


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def test_a_hundred_add_remove_cycles_leave_no_fd_thread_or_memory_behind():
    with Engine(two_heads("thread")) as eng:
        img = frame(0)

        def cycle():
            eng.add_head(DET2)
            assert "det2" in eng.wait(eng.submit(img), timeout=30)
            eng.remove_head("det2")

        for _ in range(10):  # allocators and caches settle
            cycle()
        gc.collect()
        fds, threads, rss = open_fds(), threading.active_count(), rss_mb()
        for _ in range(90):
            cycle()
        gc.collect()
        assert open_fds() == fds
        assert threading.active_count() == threads
        assert rss_mb() - rss < 40, f"{rss_mb() - rss:.1f} MB more after 90 cycles"
        assert set(eng.wait(eng.submit(img), timeout=30)) == {"depth", "seg"}


def test_process_mode_add_remove_cycles_leave_no_process_or_fd_behind():
    with Engine(two_heads("process")) as eng:
        eng.add_head(DET2)
        eng.remove_head("det2")
        procs, fds = descendants(), open_fds()
        for _ in range(4):
            eng.add_head(DET2)
            assert open_fds() > fds  # its socket, and its pidfd where the kernel has them
            assert "det2" in eng.wait(eng.submit(frame(0)), timeout=30)
            eng.remove_head("det2")
            assert open_fds() == fds  # remove_head returns with the worker's socket closed
        # the zygote has reaped each (remove_head waits for its report), but a worker killed after its grace may be
        # reported late: given until then, nothing more
        wait_for(lambda: descendants() == procs, 10, "the removed workers' exit", show=lambda: descendants() - procs)


def test_a_removal_the_monitor_is_too_busy_to_finish_returns_in_time_and_says_so(monkeypatch, caplog):
    with Engine(two_heads("process", "runtime.stop_timeout_s=0.5")) as eng:
        eng.add_head(DET2)
        runner = eng._res.runner
        monkeypatch.setattr(type(runner), "_close_retired", lambda self: None)  # the monitor never gets to it
        t0 = time.monotonic()
        try:
            with caplog.at_level("WARNING", logger="vpengine"):
                eng.remove_head("det2")
        finally:
            monkeypatch.undo()
        assert 0.5 <= time.monotonic() - t0 < 20  # the wait is bounded by stop_timeout_s, then remove_head returns
        assert any(
            "det2: the monitor did not close its worker's socket within 0.5 s" in r.getMessage() for r in caplog.records
        )
        assert runner._retired_children  # still to close
        runner._wake()
        wait_for(lambda: not runner._retired_children, 10, "the monitor's next look to close the socket")
        assert set(eng.wait(eng.submit(frame(0)), timeout=30)) == {"depth", "seg"}


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_a_mailbox_added_or_removed_while_the_engine_stops_does_not_break_the_stop(mode):
    # a removal woken by stop() drops its head's mailbox while stop() wakes every mailbox (a CI run caught it)
    eng = Engine(two_heads(mode)).start()
    rings = eng._res.rings
    assert eng._res.runner.rings is rings  # the runner wakes the engine's own dict

    class Gone:  # what a head's removal or addition does to the dict, at the worst moment
        def wake_all(self) -> None:
            rings["late"] = Late()

        def close(self) -> None:
            pass

    class Late(Gone):
        def wake_all(self) -> None:
            pass

    rings["gone"] = Gone()
    eng.stop()  # raised "dictionary changed size during iteration" before
    assert eng._res.runner is None and not descendants()


def test_a_removal_still_waiting_for_the_monitor_returns_when_the_engine_stops(monkeypatch):
    eng = Engine(two_heads("process", "runtime.stop_timeout_s=10")).start()
    runner = eng._res.runner
    took: list[float] = []
    try:
        eng.add_head(DET2)
        monkeypatch.setattr(type(runner), "_close_retired", lambda self: None)  # the monitor never gets to it

        def remove() -> None:
            t0 = time.monotonic()
            eng.remove_head("det2")
            took.append(time.monotonic() - t0)

        remover = threading.Thread(target=remove)
        remover.start()
        wait_for(lambda: runner._retired_children, 10, "det2's worker to be gone")  # the removal waits now
        assert remover.is_alive()
        eng.stop()
        remover.join(5)
        assert not remover.is_alive() and took and took[0] < 8  # with the stop, not 10 s later
    finally:
        monkeypatch.undo()
        eng.stop()
        runner._close_retired()


def test_bad_requests_are_refused_and_leave_the_engine_as_it_was():
    with Engine(two_heads("thread")) as eng:

        def unchanged():
            assert [h.name for h in eng.config.heads] == ["depth", "seg"] and eng.lanes.seats == ("+0",)
            assert set(eng.wait(eng.submit(frame(0)), timeout=30)) == {"depth", "seg"}

        with pytest.raises(ConfigError, match="unique; repeated: \\['seg'\\]"):
            eng.add_head({"name": "seg", "model": "tiny_seg"})
        with pytest.raises(ConfigError, match="heads.det2.priority"):
            eng.add_head({**DET2, "priority": 101})
        with pytest.raises(ConfigError, match="heads.det2.no_such_field: unknown key"):
            eng.add_head("{name: det2, model: tiny_det, no_such_field: 1}")
        with pytest.raises(ValueError, match="a mapping"):
            eng.add_head("just text")
        with pytest.raises(ConfigError, match="this one does not parse"):  # the live view's 400, not a 500
            eng.add_head("{name: det2, model: [tiny_det")
        with pytest.raises(ConfigError, match=r"the head's config: key 'name' is given twice in one mapping"):
            eng.add_head("{name: det2, model: tiny_det, name: det3}")
        with pytest.raises(ConfigError, match="input_mode fifo"):
            eng.add_head({**DET2, "input_mode": "fifo"})
        with pytest.raises(EngineStartError, match="injected build failure"):
            eng.add_head({"name": "bad", "model": "helpers.faulty:FaultyHead", "options": {"fail_build": True}})
        # what cannot be built is an EngineStartError, whatever raised it: a user class without from_config, a
        # checkpoint the head needs and does not have
        with pytest.raises(EngineStartError, match="head .bad. cannot be added: .*raised NotImplementedError: "):
            eng.add_head({"name": "bad", "model": "vpengine.models.base:Model"})
        with pytest.raises(EngineStartError, match="head 'det2' cannot be added: .*checkpoint"):
            eng.add_head({"name": "det2", "model": "helpers.models:DeclaredCheckpointHead", "checkpoint": "/no.pt"})
        unchanged()
        with pytest.raises(KeyError, match="no head named 'nope'; heads: \\['depth', 'seg'\\]"):
            eng.remove_head("nope")
        with pytest.raises(ValueError, match="foundation model"):
            eng.remove_head("foundation")
        eng.remove_head("seg")
        with pytest.raises(ValueError, match="last head"):
            eng.remove_head("depth")
        eng.add_head({"name": "seg", "model": "tiny_seg"})  # the name is free again; the seat takes it
        eng.set_priority("seg", 5)  # the doors know the added head
        assert eng.stats()["models"]["seg"]["priority"] == 5
        assert set(eng.wait(eng.submit(frame(1)), timeout=30)) == {"depth", "seg"}


def test_an_added_heads_worker_starts_at_its_stream_level_and_a_failed_add_puts_the_others_back(monkeypatch):
    """Note [Stream priority at run time] in runtime/device.py: the governor writes an added head's stream level
    (and the others', which it may raise) before the head's worker reads it, and puts them back if the add fails."""
    import vpengine.runtime.prepare as prepare

    started: dict[str, list[int]] = {}
    real = prepare.DeviceContext

    def noting(device, priority=0):  # type: ignore[no-untyped-def]
        started.setdefault(sys._getframe(1).f_locals["spec"].name, []).append(priority)
        return real(device, priority)

    monkeypatch.setattr(prepare, "DeviceContext", noting)
    with Engine(two_heads("thread", "runtime.spare_heads=2")) as eng:
        ctl = eng._res.control
        assert ctl is not None

        def level(model: str) -> set[int]:
            return {int(ctl.get(lane.entry, "stream_level")) for lane in eng.lanes.of(model)}

        assert started == {"foundation": [0], "depth": [0], "seg": [0]}
        eng.add_head({**DET2, "priority": 5})
        assert started["det2"] == [1]  # its level from the start, not the default and a move later
        assert (level("foundation"), level("det2"), level("depth"), level("seg")) == ({1}, {1}, {0}, {0})
        with pytest.raises(EngineStartError, match="injected build failure"):
            eng.add_head(
                {"name": "bad", "model": "helpers.faulty:FaultyHead", "options": {"fail_build": True}, "priority": 9}
            )
        assert started["bad"] == [2]  # above det2, and the foundation model with it while it was added
        assert (level("foundation"), level("det2"), level("depth")) == ({1}, {1}, {0})  # as they were
        assert set(eng.wait(eng.submit(frame(0)), timeout=30)) == {"depth", "seg", "det2"}
        # the memory report's models as they are now, not as they were at the start
        assert set(eng.stats()["memory"]["models_device_bytes"]) == {"foundation", "depth", "seg", "det2"}


def test_an_added_head_takes_its_cameras_priorities_as_they_are_now():
    cams = "cameras=[{name: front}, {name: rear}]"
    with Engine(two_heads("thread", cams)) as eng:
        eng.set_priority(None, 7, camera="rear")
        eng.add_head(DET2)
        per = eng.stats()["cameras"]
        assert per["rear"]["det2"]["camera_priority"] == 7 and per["front"]["det2"]["camera_priority"] == 0


def test_no_seat_left_says_how_to_get_one():
    with Engine(two_heads("thread", "runtime.spare_heads=0")) as eng:
        with pytest.raises(RuntimeError, match="runtime.spare_heads is 0"):
            eng.add_head(DET2)
        with pytest.raises(ConfigError, match="heads.det2.model: unknown head model 'tiny_dett'; known: "):  # first
            eng.add_head({"name": "det2", "model": "tiny_dett"})
        assert set(eng.wait(eng.submit(frame(0)), timeout=30)) == {"depth", "seg"}


def request(url: str, method: str, body: bytes | None = None) -> tuple[int, dict]:
    req = urllib.request.Request(url, data=body, method=method)
    try:
        with urllib.request.urlopen(req, timeout=120) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def test_the_live_view_adds_and_removes_heads_and_says_why_it_will_not():
    from vpengine.web import WebServer

    with Engine(two_heads("thread")) as eng, WebServer(eng, "127.0.0.1", 0) as view:
        url = view.url + "api/heads"
        assert request(url, "POST", json.dumps(DET2).encode()) == (201, {"head": "det2"})
        assert "det2" in eng.wait(eng.submit(frame(0)), timeout=30)
        status, reply = request(url, "POST", b"{name: det3, model: tiny_det}")  # YAML too
        assert status == 409 and "runtime.spare_heads is 1" in reply["error"]
        status, reply = request(url, "POST", b"{name: seg, model: tiny_seg}")
        assert status == 400 and "unique" in reply["error"]
        assert request(url + "/det2", "DELETE") == (200, {"removed": "det2"})
        status, reply = request(
            url, "POST", b"{name: bad, model: 'helpers.faulty:FaultyHead', options: {fail_build: true}}"
        )
        assert status == 422 and "injected build failure" in reply["error"]
        status, reply = request(url + "/nope", "DELETE")
        assert status == 404 and "no head named 'nope'" in reply["error"]
        assert request(url, "GET")[0] == 405
        assert set(eng.wait(eng.submit(frame(1)), timeout=30)) == {"depth", "seg"}


def test_other_callers_go_on_unharmed_while_heads_come_and_go():
    """stats, set_priority, set_rate, results and latest from other threads during add/remove cycles: no error but
    the documented ones (an unknown head while it is away), and every removed mailbox unmapped though they never stop
    calling."""
    with Engine(two_heads("thread")) as eng:
        stop, errors = threading.Event(), []
        img = frame(0)

        def call(fn):
            while not stop.is_set():
                try:
                    fn()
                except KeyError as e:  # det2 away: the documented error
                    if "det2" not in str(e):
                        errors.append(e)
                except BaseException as e:
                    errors.append(e)

        callers = [
            lambda: eng.stats(),
            lambda: eng.set_priority("det2", 3),
            lambda: eng.set_rate("det2", 20),
            lambda: eng.results(timeout=0.05),
            lambda: eng.latest("det2"),
        ]
        threads = [threading.Thread(target=call, args=(fn,), daemon=True) for fn in callers]
        for t in threads:
            t.start()
        try:
            for _ in range(15):
                eng.add_head(DET2)
                eng.wait(eng.submit(img), timeout=30)
                eng.remove_head("det2")
        finally:
            stop.set()
            for t in threads:
                t.join(10)
        assert not errors, errors[:3]
        assert not eng._res.fence._deferred  # each removed mailbox was unmapped once the calls before it ended
        assert set(eng.wait(eng.submit(img), timeout=30)) == {"depth", "seg"}


def test_stop_while_a_head_warms_up_ends_the_add_at_once():
    from vpengine.runtime.threads import _builders as builders

    eng = Engine(two_heads("thread", "runtime.stop_timeout_s=0.5")).start()  # stop gives up on the builder sooner
    slow = {"name": "slow", "model": "helpers.faulty:FaultyHead", "options": {"build_s": 30}}
    outcome = []
    adder = threading.Thread(target=lambda: outcome.append(_raised(lambda: eng.add_head(slow))))
    adder.start()
    # it builds (planning builds it too, on the meta device and at once: a stop then leaves no build behind)
    deadline = time.monotonic() + 60
    while not faulty.BUILDS_STARTED.wait(0.05):
        assert adder.is_alive() and time.monotonic() < deadline, outcome
    assert "model 'slow'" in (build_lock.holder() or "")
    t = time.monotonic()
    eng.stop()
    adder.join(20)
    try:
        assert not adder.is_alive() and time.monotonic() - t < 20
        assert outcome and isinstance(outcome[0], RuntimeError) and "stop" in str(outcome[0])
        # The build left behind holds the process's build lock until it returns (Note [One build at a time]): a new
        # engine waits its ready timeout, no longer, and says who holds it.
        t = time.monotonic()
        with pytest.raises(EngineStartError, match="model 'slow'") as e:
            Engine(two_heads("thread", "runtime.ready_timeout_s=1")).start()
        assert time.monotonic() - t < 15, e.value
        assert "no progress for runtime.ready_timeout_s = 1 s" in str(e.value)
    finally:
        faulty.BUILDS_RELEASED.set()  # the build left behind ends now, not 30 s into the next tests
    try:
        deadline = time.monotonic() + 20
        while builders.count and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not builders.count, "the released build never left"
    finally:
        faulty.BUILDS_RELEASED.clear()
        faulty.BUILDS_STARTED.clear()


def test_a_thread_mode_start_waiting_on_another_build_fails_naming_it_and_leaves_no_waiter():
    eng = Engine(two_heads("thread", "runtime.ready_timeout_s=1"))
    with held_elsewhere(build_lock, "model 'elsewhere' of engine 'other'"):  # e.g. another engine's hung build
        with pytest.raises(EngineStartError, match="model 'elsewhere' of engine 'other'"):
            eng.start()
        deadline = time.monotonic() + 10  # its workers stopped waiting: they are gone, not queued behind the holder
        while any(t.name in ("vpengine-foundation", "vpengine-depth", "vpengine-seg") for t in threading.enumerate()):
            assert time.monotonic() < deadline, threading.enumerate()
            time.sleep(0.05)


def test_an_add_waiting_to_plan_behind_another_build_ends_when_the_engine_stops():
    eng = Engine(two_heads("thread")).start()
    outcome: list[BaseException | None] = []
    with held_elsewhere(build_lock, "model 'elsewhere' of engine 'other'"):  # a build that takes its time
        adder = threading.Thread(target=lambda: outcome.append(_raised(lambda: eng.add_head(DET2))))
        adder.start()
        time.sleep(0.5)
        assert adder.is_alive()  # planning the head: its build waits for the lock
        t = time.monotonic()
        eng.stop()
        adder.join(10)
        assert not adder.is_alive() and time.monotonic() - t < 10
    assert len(outcome) == 1 and isinstance(outcome[0], EngineDeadError), outcome
    assert "stopped while det2 was being added" in str(outcome[0])


def _raised(fn):
    try:
        fn()
    except BaseException as e:
        return e
    return None


def test_a_worker_that_will_not_stop_keeps_its_seat_out_of_use(tmp_path):
    """Thread mode: a removed head whose model does not return within runtime.stop_timeout_s is abandoned; its seat
    is retired, not handed to the next head, which would share its features reader with the old thread."""
    with Engine(two_heads("thread", "runtime.stop_timeout_s=0.5", "runtime.spare_heads=2")) as eng:
        hanging = tmp_path / "hanging"  # touched as its hang begins
        options = {"hang_at_run": 1, "hang_s": 3, "once_marker": str(hanging)}
        stuck = {"name": "stuck", "model": "helpers.faulty:FaultyHead", "options": options}
        eng.add_head(stuck)
        eng.submit(frame(0))
        wait_for(hanging.exists, 30, "stuck's hang")  # it is inside its hang
        eng.remove_head("stuck")
        assert eng.lanes.seats == ("+1",)  # +0 stays out of use while its thread lives
        eng.add_head(DET2)

        def stuck_alive() -> bool:
            return any(t.name == "vpengine-stuck" for t in threading.enumerate())

        deadline, after = time.monotonic() + 30, 0
        i = 0
        while after < 3:  # the old thread wakes meanwhile and leaves; det2 is unharmed, then and after
            assert "det2" in eng.wait(eng.submit(frame(i)), timeout=30)
            assert time.monotonic() < deadline, "the abandoned thread never left"
            after += not stuck_alive()
            i += 1
            time.sleep(0.2)


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_a_head_added_for_one_of_two_cameras_serves_that_camera_only(mode):
    cfg = two_heads(mode, "cameras=[{name: front}, {name: rear}]", "runtime.spare_heads=2")
    with Engine(cfg) as eng:
        eng.add_head({**DET2, "cameras": ["rear"]})
        assert eng.lanes.seats == ("+1",) and eng.lanes.served("det2") == ["rear"]
        for i in range(3):
            front = eng.wait(eng.submit(frame(i), camera="front"), timeout=30)
            rear = eng.wait(eng.submit(frame(i), camera="rear"), timeout=30)
            assert set(front) == {"depth", "seg"} and set(rear) == {"depth", "seg", "det2"}
        assert eng.stats()["cameras"]["rear"]["det2"]["runs"] == 3 and "det2" not in eng.stats()["cameras"]["front"]
        eng.remove_head("det2")
        eng.add_head({**DET2, "cameras": ["front"]})  # the seat given back serves the other camera now
        assert set(eng.wait(eng.submit(frame(5), camera="front"), timeout=30)) == {"depth", "seg", "det2"}


def tensors_and_modules() -> tuple[int, int]:
    """Tensors and modules the garbage collector tracks: what a head left alive would hold."""
    import torch

    gc.collect()
    objects = gc.get_objects()
    kinds = [type(o) for o in objects]  # not isinstance: it asks lazy objects for their __class__
    return sum(issubclass(k, torch.Tensor) for k in kinds), sum(issubclass(k, torch.nn.Module) for k in kinds)


@pytest.mark.parametrize("backend", ["eager", pytest.param("compile", marks=INDUCTOR)])
def test_a_removed_thread_mode_head_frees_its_model_and_backend_and_cycles_leave_nothing(backend, monkeypatch):
    """Thread mode: once removed, a head's model, executor and device context (its CUDA streams: Note [Reused
    streams] in backends/streams.py) are garbage, with no collection, and cycles leave no tensor or module behind
    (on CUDA: no device memory either)."""
    import weakref

    import torch

    import vpengine.backends
    import vpengine.runtime.prepare

    built: list[weakref.ref] = []
    make_executor, device_context = vpengine.backends.make_executor, vpengine.runtime.prepare.DeviceContext

    def spy_executor(model, *args, **kw):
        ex = make_executor(model, *args, **kw)
        if args[2] == "det2":
            built.extend([weakref.ref(model), weakref.ref(ex)])
        return ex

    def spy_device(*args, **kw):
        dev = device_context(*args, **kw)
        built.append(weakref.ref(dev))
        return dev

    det2 = {**DET2, "backend": backend}
    with Engine(two_heads("thread")) as eng:
        monkeypatch.setattr(vpengine.backends, "make_executor", spy_executor)
        monkeypatch.setattr(vpengine.runtime.prepare, "DeviceContext", spy_device)  # det2's only: the rest run
        cuda = eng.config.device.startswith("cuda")

        def cycle():
            eng.add_head(det2)
            assert "det2" in eng.wait(eng.submit(frame(0)), timeout=60)
            eng.remove_head("det2")
            assert set(eng.wait(eng.submit(frame(1)), timeout=30)) == {"depth", "seg"}

        gc.disable()  # garbage by reference counting alone: removing a head runs no collection (heads.py)
        try:
            cycle()
        finally:
            gc.enable()
        assert len(built) == 3  # the spies saw det2's model, executor and device context
        assert [r() for r in built] == [None] * 3, "a removed head's model, executor or device context is alive"
        cycle()  # caches (dynamo's, the allocator's, the streams') settle
        held = tensors_and_modules()
        if cuda:
            torch.cuda.synchronize()
        device_bytes = torch.cuda.memory_allocated() if cuda else 0
        for _ in range(3):
            cycle()
        assert all(r() is None for r in built)
        now = tensors_and_modules()
        assert now[0] <= held[0] and now[1] <= held[1], f"(tensors, modules): {now} after 3 cycles, {held} before"
        if cuda:
            torch.cuda.synchronize()
            assert torch.cuda.memory_allocated() <= device_bytes


@pytest.mark.skipif(not full_collections_can_be_held_off(), reason="an incremental collector")
def test_a_head_is_built_with_a_short_switch_interval_and_no_full_collection_then_its_heap_stays_frozen(
    monkeypatch,
):
    """Note [Building beside serving threads]: the serving threads get the interpreter lock back often, and the
    garbage collector runs no full collection, while a head builds beside them; after the add the interval and the
    collector's thresholds are as they were and the heap stays frozen until the engine stops. The engine's start
    (nothing serves) changes nothing. Only the added head's worker is prepared as one built beside serving threads
    (Note [Compile workers]: on CUDA a compiled one waits for inductor's compile workers)."""
    import sys

    import vpengine.runtime.plan
    import vpengine.runtime.prepare
    import vpengine.runtime.threads
    from vpengine.runtime.threads import BUILD_SWITCH_INTERVAL_S, _builders

    prepared_beside: dict[str, bool] = {}
    prepare_worker = vpengine.runtime.threads.prepare_worker

    def prepare_spy(spec, *args, beside_serving=False, **kw):
        prepared_beside[spec.name] = beside_serving
        return prepare_worker(spec, *args, beside_serving=beside_serving, **kw)

    monkeypatch.setattr(vpengine.runtime.threads, "prepare_worker", prepare_spy)

    seen: dict[str, list[tuple[float, bool, bool]]] = {}
    build_model = vpengine.runtime.prepare.build_model

    def spy(cfg, name, *args, plan_only, **kw):
        state = (sys.getswitchinterval(), gc.get_freeze_count() > 0, gc.get_threshold()[2] > 10**9)
        seen.setdefault(f"{name} on meta" if plan_only else name, []).append(state)
        return build_model(cfg, name, *args, plan_only=plan_only, **kw)

    monkeypatch.setattr(vpengine.runtime.prepare, "build_model", spy)
    monkeypatch.setattr(vpengine.runtime.plan, "build_model", spy)  # the add's planning, in the caller's thread
    before = (sys.getswitchinterval(), gc.get_threshold())
    assert before[0] > BUILD_SWITCH_INTERVAL_S
    assert not _builders.holders and _builders.count == 0  # no engine or build before kept the heap frozen
    gc.unfreeze()  # something else froze it (seen on the GPU machine): not this test's
    with Engine(two_heads("thread")) as eng:
        eng.add_head(DET2)
        assert (sys.getswitchinterval(), gc.get_threshold(), gc.get_freeze_count() > 0) == (*before, True)
        assert "det2" in eng.wait(eng.submit(frame(0)), timeout=30)
    assert gc.get_freeze_count() == 0 and not _builders.holders
    at_start, beside = (before[0], False, False), (BUILD_SWITCH_INTERVAL_S, True, True)
    assert seen["foundation"] == seen["depth"] == seen["seg"] == [at_start]
    assert seen["foundation on meta"][0] == at_start and seen["foundation on meta"][-1] == beside  # start, add
    assert seen["det2 on meta"] == seen["det2"] == [beside]
    assert prepared_beside == {"foundation": False, "depth": False, "seg": False, "det2": True}
