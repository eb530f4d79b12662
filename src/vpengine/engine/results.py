"""What a head's output becomes for the caller, and how the engine takes results out of the output mailboxes.

:class:`Outbox` is the engine's side of every head's output mailbox: it pins results (only those whose device work is
done, Note [Result hand-off] in runtime/handoff.py), maps them back to their frame's grid (Note [Frame grid] in
boundary.py), lends or copies them (Note [Borrowed results]) and finds a frame's results for ``Engine.wait`` (Note
[Answered frames] in runtime/worker.py). The engine's API methods check that it is running and delegate here.

Note [Borrowed results]
~~~~~~~~~~~~~~~~~~~~~~~
By default a result's host arrays are the caller's own copies. With ``copy=False`` (``wait``, ``results``,
``latest``) they are read-only views of the head's output slot instead: eight 1080p float32 depth maps are 66 MB a
frame, and copying them costs more than the heads' GPU time on a fast GPU. A borrowed slot is pinned by one of the
head's ``LEASES`` (2) lease readers, so the head never writes into it while anything refers to the arrays (no
torn reads); once the last array, view of one, or tensor made from one is gone, the lease goes back at the next
``wait``/``results``/``latest`` call. With every lease of a head out, further results of that head are copies
(``Result.borrowed`` says which). The mapping outlives ``stop()`` as long as a view of it does.

"""

from __future__ import annotations

import collections
import concurrent.futures
import functools
import logging
import sys
import threading
import time
import weakref
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from vpengine.config import DEFAULT_CAMERA
from vpengine.engine.boundary import Boundary, Placement, drop_empty_boxes
from vpengine.models.base import Model
from vpengine.runtime.control import NOT_SERVING, POLL_S, ControlBlock
from vpengine.runtime.handoff import Handoffs
from vpengine.runtime.lanes import Lanes
from vpengine.runtime.plan import LEASES
from vpengine.runtime.supervisor import EngineDeadError
from vpengine.transport.ring import Accept, RingReader, SlotInfo, SlotRing

log = logging.getLogger("vpengine")

_RECYCLED_PER_OUTPUT = 2  # host arrays kept per (head, camera, output) for reuse once the user has let go of them


def _refcounts(pool: list[np.ndarray]) -> list[int]:
    return [sys.getrefcount(a) for a in pool]


# what _refcounts reports for an array that only the pool list refers to (differs between Python versions)
_FREE_REFS = _refcounts([np.empty(1)])[0]


class _HostOutputs:
    """Host arrays for results, recycled: copying a 1080p float32 depth map into fresh memory costs page faults on
    every frame (eight of them are 66 MB), so an array is reused once nothing outside this pool refers to it
    (a view or a tensor made from it refers to it too). Kept per camera: every camera's result of a tick is handed
    out at once, so a pool shared by the cameras would give all but its first ``_RECYCLED_PER_OUTPUT`` results
    fresh memory on every tick; the allocator then maps and unmaps it whenever results bunch up, and each of those
    page faults lands on a late frame (Note [First batch] in runtime/worker.py: serving maps no new memory). Outputs
    mapped to their frame's grid (Note [Frame grid] in boundary.py) are written into these arrays too, at the
    frame's size. Bounded: at most ``_RECYCLED_PER_OUTPUT`` arrays per (head, camera, output) are kept (eight cameras'
    1080p float32 depth maps: 133 MB), each of a size still asked for: a free one of another size goes once another
    size is asked for (a camera's frames changed size, or one odd frame came). Beyond that results get fresh arrays
    that are not tracked."""

    def __init__(self) -> None:
        self._pools: dict[tuple[str, int, str], list[np.ndarray]] = {}

    def forget(self, head: str) -> None:
        self._pools = {k: v for k, v in self._pools.items() if k[0] != head}

    def copy(self, head: str, camera: int, key: str, src: np.ndarray) -> np.ndarray:
        """``src`` copied into a free array of ``head``'s ``key`` for the camera of tag ``camera`` (or a new one)."""
        arr = self.take(head, camera, key, src.shape, src.dtype)
        np.copyto(arr, src)
        return arr

    def take(self, head: str, camera: int, key: str, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        """An array of ``shape`` and ``dtype`` to write ``head``'s ``key`` for the camera of tag ``camera`` into: a
        kept one that nothing refers to, else a new one, kept where there is room or in place of a free one of
        another shape (outputs mapped to a frame's grid take the frame's size, which may change)."""
        pool = self._pools.setdefault((head, camera, key), [])
        free = [i for i, refs in enumerate(_refcounts(pool)) if refs <= _FREE_REFS]
        fits = [i for i in free if pool[i].shape == shape and pool[i].dtype == dtype]
        if fits:
            arr = pool[fits[0]]
            # a free array of a size no longer asked for goes: one odd frame's outputs are not kept for good
            pool[:] = [a for i, a in enumerate(pool) if i not in free or i in fits]
            return arr
        arr = np.empty(shape, dtype)
        if len(pool) < _RECYCLED_PER_OUTPUT:
            pool.append(arr)
        elif free:
            pool[free[0]] = arr
        return arr


def _numpy_output(t: torch.Tensor) -> bool:
    """Whether an output slot tensor is handed out as a numpy array (host, and a dtype numpy has), not a tensor."""
    return t.device.type == "cpu" and t.dtype != torch.bfloat16


class _Lease:
    """Keeps a borrowed slot pinned: every array of a borrowed result refers to it; when the last one goes, its
    finalizer hands the lease reader back (queued, not released there: a finalizer may run inside a ring's critical
    section of this very thread, whose mutex is not re-entrant)."""

    __slots__ = ("__weakref__", "mapping")

    def __init__(self, mapping: object) -> None:
        self.mapping = mapping  # keeps the slot's memory mapped, even past stop()


class _SlotView:
    """What ``np.asarray`` turns into a read-only array over a slot tensor; the array's base, holding the lease."""

    __slots__ = ("__array_interface__", "_lease")

    def __init__(self, iface: dict[str, Any], lease: _Lease) -> None:
        self.__array_interface__ = iface
        self._lease = lease


def _read_only_interface(tensor: torch.Tensor) -> dict[str, Any]:
    iface = dict(tensor.numpy().__array_interface__)
    iface["data"] = (iface["data"][0], True)  # read-only
    return iface


class _Leases:
    """Lease readers of every head's output ring (Note [Borrowed results])."""

    def __init__(self, readers: dict[str, list[RingReader]]) -> None:
        self.free = {h: list(rs) for h, rs in readers.items()}
        self.total = {h: len(rs) for h, rs in readers.items()}
        self.rings = {h: rs[0].ring for h, rs in readers.items()}  # each head's output mailbox now
        self.returned: collections.deque[tuple[str, RingReader]] = collections.deque()
        # (head, slot index) -> key -> array interface: a slot's tensors never move, and borrowing runs right after
        # the caller wakes, where every call costs several times what it does in a loop (Note [Launch path])
        self._interfaces: dict[tuple[str, int], dict[str, dict[str, Any]]] = {}

    def drain(self) -> None:
        """Release the slots whose results nobody refers to any more (caller holds the engine's read lock)."""
        while self.returned:
            head, reader = self.returned.popleft()
            if reader.ring is not self.rings.get(head):
                continue  # its head was removed meanwhile (and maybe added anew): that mailbox is gone
            reader.release()
            self.free[head].append(reader)

    def add(self, head: str, readers: list[RingReader]) -> None:
        self.free[head], self.total[head], self.rings[head] = list(readers), len(readers), readers[0].ring

    def remove(self, head: str) -> None:
        self.free.pop(head, None)
        self.total.pop(head, None)
        self.rings.pop(head, None)
        self._interfaces = {k: v for k, v in self._interfaces.items() if k[0] != head}

    def borrow(self, head: str, slot: SlotInfo) -> dict[str, np.ndarray] | None:
        """Read-only arrays over ``slot`` (pinned by the caller's reader), or None if no lease is free."""
        free = self.free.get(head)
        if not free:
            return None
        reader = free[-1]
        held = reader.pin_slot(slot)
        if held is None:
            return None
        free.pop()
        lease = _Lease(reader.ring.data_region.keep_mapped())
        weakref.finalize(lease, self.returned.append, (head, reader))
        ifaces = self._interfaces.get((head, held.index))
        if ifaces is None:
            ifaces = {k: _read_only_interface(t) for k, t in held.tensors.items()}
            self._interfaces[(head, held.index)] = ifaces
        return {k: np.asarray(_SlotView(iface, lease)) for k, iface in ifaces.items()}

    def held(self, head: str) -> int:
        return self.total[head] - len(self.free[head])


@dataclass
class Result:
    """One head's output for one frame."""

    head: str
    frame_id: int
    #: The frame's capture time as given to submit (or the wall-clock time of submit), seconds since the epoch.
    capture_time: float
    #: Seconds from submit to this output being on the host (published, and its device work done).
    latency: float
    #: Output tensors: numpy arrays (host outputs) or torch tensors (device outputs, bfloat16). A host array's memory
    #: is reused for a later result of the same head and camera once nothing refers to the array (nor to any view of
    #: it) any more, so keeping a reference (or a view, or ``torch.from_numpy`` of it) keeps its content.
    outputs: dict[str, Any]
    seq: int = 0
    #: When the output was there to read (``time.monotonic()``).
    t_publish: float = 0.0
    #: True: the host arrays are read-only views of the head's output slot, kept for as long as they are referenced
    #: (Note [Borrowed results]); False: they are copies.
    borrowed: bool = False
    #: (height, width) of the submitted frame.
    frame_size: tuple[int, int] = (0, 0)
    #: "frame": maps at the frame's size, boxes in its pixels (the default); "native": in the models' input grid,
    #: as the head's ``output.grid: native`` asks (Note [Frame grid] in boundary.py).
    grid: str = "frame"
    #: Where the frame lies in the models' input grid; maps native outputs to the frame's grid.
    placement: Placement | None = None
    #: The frame as a BGR uint8 picture (the frame itself for the default input: BGR uint8), for results of
    #: ``Engine.predict`` (others: None; the engine keeps no frames).
    image: np.ndarray | None = None
    #: The head's metadata (kind, labels, palette), for drawing.
    info: dict[str, Any] = field(default_factory=dict, repr=False)
    #: The camera the frame came from (Note [Cameras] in runtime/worker.py).
    camera: str = DEFAULT_CAMERA
    #: For a result in the native grid: its outputs mapped to the frame's grid, as ``plot`` draws them.
    _in_frame_grid: Callable[[dict[str, Any], Placement | None], dict[str, Any]] | None = field(
        default=None, repr=False, compare=False
    )

    def __getitem__(self, key: str) -> Any:
        return self.outputs[key]

    def plot(self, image: np.ndarray | None = None) -> np.ndarray:
        """This result drawn as a BGR uint8 picture at its frame's size: on ``image`` (a BGR uint8 picture of the
        frame) when given, else on the predicted frame (``self.image``), else on its own (depth colours with a bar,
        class colours, boxes on black)."""
        from vpengine.visualize import draw_result

        frame = self.image if image is None else image
        if frame is None and self.info.get("kind") == "detection":
            frame = np.zeros((*self.frame_size, 3), np.uint8)
        outputs = self.outputs if self._in_frame_grid is None else self._in_frame_grid(self.outputs, self.placement)
        return draw_result(frame, outputs, self.info, self.head)


class Outbox:
    """The engine's readers of every head's output mailbox, and what turns a pinned slot into a :class:`Result`.

    ``placements`` maps a frame's origin (its input seq) to where it lies in the models' input grid; the engine adds
    to it as frames come in. Thread-safe: one read lock guards the readers. It is not held while a call waits for an
    output to be published; it is held while a pinned result's device work is waited for and the result copied, so
    one camera's results are read after another's. Tried instead: a reader a camera, each camera's results read
    outside the lock. That removed the waits for the lock but not the time: the callers then waited for the device
    side by side, taking turns at the interpreter lock the heads' threads launch their work with, and four cameras'
    frames per second on a GPU fell."""

    def __init__(
        self,
        rings: Mapping[str, SlotRing],
        heads: Mapping[str, Model],
        control: ControlBlock,
        handoffs: Handoffs,
        boundary: Boundary,
        placements: Mapping[int, Placement],
        lanes: Lanes,
    ) -> None:
        self.heads = heads
        self.control = control
        self.handoffs = handoffs
        self.boundary = boundary
        self.placements = placements
        self.lanes = lanes  # Note [Lanes] in runtime/lanes.py
        self._results_readers = {h: rings[f"out.{h}"].reader("results") for h in heads}
        self._peek_readers = {h: rings[f"out.{h}"].reader("peek") for h in heads}
        self.leases = _Leases({h: [rings[f"out.{h}"].reader(f"lease{i}") for i in range(LEASES)] for h in heads})
        self._rings = rings
        self._lock = threading.Lock()
        self._streaming = False
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None
        self._host_outputs = _HostOutputs()
        self._numpy_heads: dict[str, bool] = {}  # head -> its outputs are handed out as numpy arrays
        self._told_not_lent: set[str] = set()  # heads whose copy=False results were copied for their grid, said once

    def add_head(self, name: str, model: Model, ring: SlotRing, lanes: Lanes) -> None:
        """Serve the results of a head added at run time (Note [Heads at run time] in runtime/lanes.py)."""
        with self._lock:
            results = ring.reader("results")
            if self._streaming:
                results.activate(from_now=True)
            self._results_readers = {**self._results_readers, name: results}
            self._peek_readers = {**self._peek_readers, name: ring.reader("peek")}
            self.leases.add(name, [ring.reader(f"lease{i}") for i in range(LEASES)])
            self.heads, self.lanes = {**self.heads, name: model}, lanes

    def remove_head(self, name: str, lanes: Lanes) -> None:
        """Stop serving a head removed at run time; its mailbox is unmapped once no call holds it."""
        with self._lock:
            self.heads = {h: m for h, m in self.heads.items() if h != name}
            self._results_readers = {h: r for h, r in self._results_readers.items() if h != name}
            self._peek_readers = {h: r for h, r in self._peek_readers.items() if h != name}
            self.leases.remove(name)
            self._numpy_heads.pop(name, None)
            self._host_outputs.forget(name)
            self.lanes = lanes

    def head(self, head: str) -> str:
        if not isinstance(head, str):
            raise ValueError(f"a head is named by a str, got {head!r}")
        if head not in self.heads:
            raise KeyError(f"no head named {head!r}; heads: {list(self.heads)}")
        return head

    # ------------------------------------------------------------------------------------------ the API
    def latest(self, head: str, copy: bool, camera: int | None = None) -> Result | None:
        """``head``'s newest result, of camera (slot tag) ``camera`` only unless None."""
        reader = self._peek_readers[self.head(head)]
        accept = self._done_filter(head)
        if camera is not None:
            ring, done = self._rings[f"out.{head}"], accept
            accept = lambda i, seq: ring.slot_tag(i) == camera and (done is None or done(i, seq))  # noqa: E731
        with self._lock:
            self.leases.drain()
            slot = reader.pin(peek=True, accept=accept)
            if slot is None:
                return None
            try:
                return self._to_result(head, slot, None if copy else self._borrow(head, slot))
            finally:
                reader.release(slot)

    def results(self, timeout: float, heads: list[str] | None, copy: bool, alive: Callable[[], bool]) -> list[Result]:
        ctl = self.control
        names = [self.head(h) for h in heads] if heads else list(self._results_readers)
        deadline = time.monotonic() + timeout
        while True:
            word = ctl.output_word()
            with self._lock:  # not held while sleeping below: latest() and wait() from other threads go on
                self.leases.drain()
                if not self._streaming:
                    for r in self._results_readers.values():
                        r.activate(from_now=True)
                    self._streaming = True
                out: list[Result] = []
                more = list(names)
                while more:  # one slot per head at a time (a reader holds one pin), heads copied in parallel
                    pinned: list[tuple[str, SlotInfo]] = []
                    try:
                        for h in more:
                            if h not in self._results_readers:
                                continue  # removed meanwhile
                            slot = self._results_readers[h].pin(accept=self._done_filter(h))
                            if slot is not None:
                                pinned.append((h, slot))
                        out.extend(self._copy_out(pinned, copy).values())
                    finally:
                        for h, slot in pinned:
                            self._results_readers[h].release(slot)
                    more = [h for h, _ in pinned]
            remaining = deadline - time.monotonic()
            if out or remaining <= 0 or not alive():
                return sorted(out, key=lambda r: r.t_publish)
            ctl.wait_output(word, min(remaining, POLL_S))

    def wait(
        self,
        origin: int,
        camera: int,
        frame_id: int,
        heads: list[str] | None,
        timeout: float,
        copy: bool,
        alive: Callable[[], bool],
    ) -> dict[str, Result]:
        ctl = self.control
        pending = [self.head(h) for h in heads] if heads else list(self.heads)
        # a head that does not serve the frame's camera gives no output for it
        entries = {h: lane.entry for h in ["foundation", *pending] if (lane := self.lanes.find(h, camera)) is not None}
        pending = [h for h in pending if h in entries]

        def entry(model: str) -> str:
            return entries[model]

        done: dict[str, Result] = {}
        deadline = time.monotonic() + timeout
        while True:
            word = ctl.output_word()
            # Note [Answered frames]: read before looking for outputs; a frame the foundation held back reaches no head
            f_decided = ctl.get(entry("foundation"), "decided")  # before last_run, which decide() stores first
            f_ran = ctl.get(entry("foundation"), "last_run") >= origin
            held_back = not f_ran and (f_decided >= origin or ctl.rate(entry("foundation")) == 0)
            with self._lock:
                self.leases.drain()
                found: list[tuple[str, SlotInfo]] = []
                try:
                    for h in list(pending):
                        reader = self._peek_readers.get(h)
                        if reader is None:  # removed meanwhile: it answers nothing more
                            pending.remove(h)
                            continue
                        answered = held_back or ctl.get(entry(h), "decided") >= origin
                        slot, newest = reader.pin_origin(origin, tag=camera)  # Note [Tagged slots]
                        events = self.handoffs.results.get(h)
                        if slot is not None and events is not None and events.done_after(slot, deadline):
                            # Note [Result hand-off]: its queued work is not expected to be done in time; leave
                            # it until its head says it is done (or the timeout), rather than wait past it
                            reader.release(slot)
                            continue
                        if slot is not None:
                            found.append((h, slot))
                        if (
                            slot is not None
                            or answered
                            or newest > origin
                            or ctl.state(h) in NOT_SERVING
                            or ctl.rate(entry(h)) == 0  # paused: answers nothing (one already running still may)
                        ):
                            pending.remove(h)
                    done.update(self._copy_out(found, copy))
                finally:
                    for h, slot in found:
                        slot_reader = self._peek_readers.get(h)
                        if slot_reader is not None:
                            slot_reader.release(slot)
            remaining = deadline - time.monotonic()
            if not pending:
                return done
            if remaining <= 0:
                raise TimeoutError(
                    f"frame {frame_id}: no output from {pending} within {timeout} s (got {sorted(done)})"
                )
            if not alive():
                raise EngineDeadError("engine stopped while waiting")
            ctl.wait_output(word, min(remaining, POLL_S))

    def stats(self) -> dict[str, dict[str, Any]]:
        """Per head: published, delivered to results(), missed by it, pending, dropped, streaming, borrowed."""
        out = {}
        for h in self.heads:
            ring = self._rings.get(f"out.{h}")
            if ring is None:
                continue  # removed meanwhile
            st = ring.stats()
            rr = st["readers"]["results"]  # type: ignore[index]
            out[h] = {
                "published": st["published"],
                "delivered": rr["reads"],
                "missed": rr["missed"],
                "pending": rr["pending"],
                "dropped_newest": st["dropped_newest"],
                "streaming": rr["active"],
                "borrowed": self.leases.held(h),
            }
        return out

    # ------------------------------------------------------------------------------------------ slots
    def _done_filter(self, head: str) -> Accept | None:
        """Note [Result hand-off]: the pin filter that takes only ``head``'s results whose device work is done."""
        events = self.handoffs.results.get(head)
        return None if events is None else events.done

    def _borrow(self, head: str, slot: SlotInfo) -> dict[str, np.ndarray] | None:
        """Read-only arrays over pinned ``slot``'s host outputs (Note [Borrowed results]), or None (no lease free,
        an output that is not a numpy array, or outputs mapped to the frame's grid). Their content is there only
        once ``wait_done`` says so."""
        numpy = self._numpy_heads.get(head)
        if numpy is None:  # a head's outputs are host arrays, or not, in every slot
            numpy = self._numpy_heads[head] = all(_numpy_output(t) for t in slot.tensors.values())
        if not numpy:
            return None
        change = self._grid_change(head, slot)
        if change is not None:  # outputs mapped to another grid are not the slot's: nothing to lend
            if head not in self._told_not_lent:
                self._told_not_lent.add(head)
                h, w = change.frame_hw
                log.warning(
                    "%s: copy=False results are copies: the frame (%dx%d) is not the models' input size, so its "
                    "outputs are mapped to the frame's grid in new arrays (output.grid: native would lend them in "
                    "the models' grid)",
                    head,
                    w,
                    h,
                )
            return None
        return self.leases.borrow(head, slot)

    def _grid_change(self, head: str, slot: SlotInfo) -> Placement | None:
        """The placement to map ``head``'s output in ``slot`` back to its frame's grid, or None (same grid, or the
        head keeps the native grid)."""
        p = self.placements.get(slot.origin)
        if p is None:  # pragma: no cover - kept for far more frames than any mailbox holds
            raise RuntimeError(f"no record of the frame behind {head}'s output for frame {slot.frame_id}")
        return None if p.identity or head in self.boundary.native else p

    def _to_result(self, head: str, slot: SlotInfo, borrowed: dict[str, np.ndarray] | None = None) -> Result:
        """``head``'s result from pinned ``slot`` once its device work is done: ``borrowed``, ``_borrow``'s arrays
        (taken before the wait), or else copied."""
        events = self.handoffs.results.get(head)  # Note [Result hand-off]
        t_ready = slot.t_publish if events is None else events.wait_done(slot)
        outputs: dict[str, Any]
        change = self._grid_change(head, slot)
        if borrowed is not None:
            outputs = borrowed
        elif change is not None:  # Note [Frame grid]: mapped straight out of the slot, 2-D maps into the kept arrays
            kinds = self.boundary.kinds[head]
            outputs = {}
            for k, t in slot.tensors.items():
                v = t.numpy() if _numpy_output(t) else t
                if k in kinds:
                    outputs[k] = change.to_frame(
                        kinds[k], v, alloc=functools.partial(self._host_outputs.take, head, slot.tag, k)
                    )
                else:
                    outputs[k] = (
                        self._host_outputs.copy(head, slot.tag, k, v) if isinstance(v, np.ndarray) else t.clone()
                    )
        else:
            outputs = {
                k: self._host_outputs.copy(head, slot.tag, k, t.numpy()) if _numpy_output(t) else t.clone()
                for k, t in slot.tensors.items()
            }
        # Note [Empty boxes] in boundary.py: in every grid and every way of handing out (a borrowed result's box rows
        # become copies only when one is dropped)
        outputs = drop_empty_boxes(outputs, self.boundary.kinds[head])
        if all(isinstance(v, np.ndarray) for v in outputs.values()):
            outputs = self.heads[head].finalize(outputs)
        p = self.placements[slot.origin]
        return Result(
            head,
            slot.frame_id,
            slot.t_capture,
            t_ready - slot.t_submit,
            outputs,
            slot.seq,
            t_ready,
            borrowed=borrowed is not None,
            frame_size=p.frame_hw,
            grid="native" if head in self.boundary.native else "frame",
            placement=p,
            info=self.heads[head].meta,
            camera=self.lanes.cameras[slot.tag],
            _in_frame_grid=functools.partial(self.boundary.to_frame, head) if head in self.boundary.native else None,
        )

    def _copy_out(self, pinned: list[tuple[str, SlotInfo]], copy: bool = True) -> dict[str, Result]:
        """Results for pinned slots. Borrowed ones are borrowed before any is waited for, so that what can be done
        while the device finishes is done by then. Several heads' outputs are copied at once (numpy releases the
        GIL), which matters with many full-resolution outputs: eight 1080p float32 depth maps are 64 MB per frame."""
        small = sum(t.nbytes for _, s in pinned for t in s.tensors.values()) < 4 << 20
        if not copy or len(pinned) <= 1 or small:
            borrowed = [None if copy else self._borrow(h, s) for h, s in pinned]
            return {h: self._to_result(h, s, b) for (h, s), b in zip(pinned, borrowed)}
        if self._pool is None:
            self._pool = concurrent.futures.ThreadPoolExecutor(
                max_workers=min(8, len(self.heads)), thread_name_prefix="vpe-copy"
            )
            weakref.finalize(self, self._pool.shutdown, wait=False)
        futures = {h: self._pool.submit(self._to_result, h, s) for h, s in pinned}
        # every copy finished before any error is raised: the caller releases the pinned slots on an error, and a
        # copy still reading one would read a slot being written again (and race a later copy into the same array)
        concurrent.futures.wait(futures.values())
        return {h: f.result() for h, f in futures.items()}
