"""Lanes: the (model, camera) pairs of an engine, described once at plan time and handed to everyone.

Note [Lanes]
~~~~~~~~~~~~
A *lane* is one model's share of one camera's frames: the camera's name and tag (its index in the configured order,
which tags its frames' slots, Note [Tagged slots] in transport/ring.py), the model's reader of its input ring for that
camera, and the model's control-block entry for it (rate, counters, latencies, answered frames; Note [Answered frames]
in worker.py), and the rate it starts with. :func:`make_lanes` builds them from the config once (``Plan.lanes``), and
the engine, the workers (``WorkerSpec.lanes``), the supervisor, the results and the control block's layout all read them
from there: this module is the only one that turns a camera into its index, reader or entry (a test in
tests/unit/test_lanes.py keeps it so). One camera is the case of one lane per model: its reader and entry are then the
model's own name (which keeps one-camera stats and ring names as they always were); with several cameras both are
``model@camera``.

Note [Heads at run time]
~~~~~~~~~~~~~~~~~~~~~~~~
Every mailbox and the control block are laid out at start, in shared memory other processes have mapped, so a head
added while the engine runs (``Engine.add_head``) cannot grow them. Instead the engine starts with
``runtime.spare_heads`` *seats*: a seat is a model that is not there, named ``+0``, ``+1``, ... (no head can be: head
names are identifiers), with a lane on every camera, hence its control-block entries and an inactive reader of the
features mailbox per camera (and one more features slot for it to pin). A head added takes a free seat: its entries
and readers are renamed to its own lanes' names (``seat_renames``) in the engine's process before its worker, which
attaches with the new names, starts; the other workers address readers and entries by index and never notice.
Its own output mailbox is new. Removing it stops its worker, clears its entries and readers and gives their names
back to the seat. So a head added runs exactly like one configured, and the engine's preallocation holds: adding a
head allocates its output mailbox and its model, nothing that other models share.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from vpengine.config import EngineConfig


@dataclass(frozen=True)
class Lane:
    """One (model, camera) pair. Picklable: it crosses into a worker's child process in ``WorkerSpec``."""

    model: str
    camera: str
    tag: int  # the camera's index in the configured order: the tag of its frames' slots
    reader: str  # the model's reader of its input ring for this camera
    entry: str  # the model's control-block entry for this camera
    only: bool  # the engine's only camera: its readers take every slot, untagged
    rate_hz: float | None  # the configured rate limit it starts with (None: unlimited; set_rate changes the entry's)

    @property
    def reader_tag(self) -> int | None:
        """The slot tag this lane's reader takes (Note [Tagged slots]); None (every slot) with one camera."""
        return None if self.only else self.tag


@dataclass(frozen=True)
class Lanes:
    """Every lane of an engine: per model (``foundation`` first, then the heads), the cameras it serves in priority
    order."""

    cameras: tuple[str, ...]
    by_model: Mapping[str, tuple[Lane, ...]]
    #: the free seats of heads added at run time (Note [Heads at run time]), in order
    seats: tuple[str, ...] = ()

    def of(self, model: str) -> tuple[Lane, ...]:
        """``model``'s lanes, in the configured order of their cameras; KeyError naming the models for an unknown one."""
        try:
            return self.by_model[model]
        except KeyError:
            raise KeyError(f"no model named {model!r}; models: {list(self.by_model)}") from None

    def served(self, model: str) -> list[str]:
        """The cameras ``model`` serves, in the configured order."""
        return [lane.camera for lane in self.of(model)]

    def tag(self, camera: str | None) -> int:
        """The tag of ``camera``; None: the only camera's. ValueError naming the cameras otherwise."""
        if camera is None:
            if len(self.cameras) > 1:
                raise ValueError(f"this engine has cameras {list(self.cameras)}: say which one with camera=")
            return 0
        if camera not in self.cameras:
            raise ValueError(f"no camera named {camera!r}; cameras: {list(self.cameras)}")
        return self.cameras.index(camera)

    def find(self, model: str, tag: int) -> Lane | None:
        """``model``'s lane for the camera tagged ``tag``, or None if it does not serve that camera."""
        for lane in self.of(model):
            if lane.tag == tag:
                return lane
        return None

    def select(self, model: str, camera: str | None) -> tuple[Lane, ...]:
        """``model``'s lane for ``camera`` (None: all its lanes); ValueError for a camera it does not serve."""
        lanes = self.of(model)
        if camera is None:
            return lanes
        found = [lane for lane in lanes if lane.camera == camera]
        if not found:
            raise ValueError(f"{model!r} serves cameras {self.served(model)}, not {camera!r}")
        return tuple(found)

    def control_names(self) -> list[str]:
        """Every entry of the control block: each model's own (process state, heartbeat, errors; with one camera
        its lane's too), then every lane's that is not its model's; then the same for each free seat."""
        models = {**self.by_model, **{seat: self.seat_lanes(seat) for seat in self.seats}}
        own = list(models)
        return own + [lane.entry for lanes in models.values() for lane in lanes if lane.entry not in own]

    def seat_lanes(self, seat: str) -> tuple[Lane, ...]:
        """A free seat's lanes: one on every camera, whose readers wait, inactive, in the features mailbox."""
        return tuple(_lane(seat, camera, self.cameras, None) for camera in self.cameras)

    def seat_renames(self, seat: str, head: str) -> dict[str, str]:
        """What ``head``, taking ``seat``, renames the seat's entries and readers to: the seat's own entry to the
        head's, and its lane on each camera the head serves to the head's lane there."""
        renames = {seat: head}
        for mine in self.of(head):
            renames[_lane(seat, mine.camera, self.cameras, None).entry] = mine.entry
        return renames


def _lane(model: str, camera: str, cameras: tuple[str, ...], rate_hz: float | None) -> Lane:
    only = len(cameras) == 1
    name = model if only else f"{model}@{camera}"
    return Lane(model, camera, cameras.index(camera), reader=name, entry=name, only=only, rate_hz=rate_hz)


def make_lanes(cfg: EngineConfig, seats: tuple[str, ...] | None = None) -> Lanes:
    """The lanes of the engine ``cfg`` describes (Note [Lanes]); ``seats``: its free seats (Note [Heads at run
    time]; default: all of ``runtime.spare_heads``)."""
    cameras = tuple(cfg.camera_names())
    by_model = {
        m: tuple(_lane(m, c, cameras, cfg.model(m).rate_hz) for c in cfg.model_cameras(m)) for m in cfg.model_names()
    }
    if seats is None:
        seats = tuple(f"+{k}" for k in range(cfg.runtime.spare_heads))
    return Lanes(cameras, by_model, seats)
