"""Building a model of a config: the one way every caller (workers, planning, export, training, benchmarks) does it.

``build_model`` resolves the config's recipe, builds it (on the meta device with no weights while planning, else on
the given device with its checkpoint loaded) and leaves it in eval mode with gradients off.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import torch

from vpengine.config import EngineConfig
from vpengine.models.base import BuildContext, Model, ModelBuildError, Role
from vpengine.models.registry import resolve
from vpengine.specs import SpecDict, TensorSpec

log = logging.getLogger(__name__)

# Note [One build at a time]
# ~~~~~~~~~~~~~~~~~~~~~~~~~~
# A model is constructed, and a worker captures its CUDA graphs, under the process's one ``build_lock``.
# Construction draws from PyTorch's process-global RNG (default layer init, seeded random weights), so thread-mode
# workers building at once would interleave their draws and get weights that differ from run to run (and from
# process mode); a graph capture must not overlap a build whose layer init draws from the CUDA RNG that the capture
# has claimed (seen on an H100).
#
# A build cannot be interrupted, so the lock is held until the build returns, even when nobody waits for it any more
# (a stop or a failed add_head abandons a thread-mode build) or never (a user's constructor that hangs). So nobody
# waits for it blindly: a waiter gives up when its engine stops waiting (``cancelled``) and once the holder has made
# no progress (``step``: Note [Start progress] in runtime/supervisor.py) for its config's ``runtime.ready_timeout_s``
# (a holder compiling batch size after batch size is slow, not stuck), and both that error and a log line after
# WAIT_LOG_S of waiting name the holder.

WAIT_LOG_S = 5.0  # a wait this long is worth a line in the log: a start looks stuck otherwise


class BuildLockTimeout(RuntimeError):
    """A build waited its ``runtime.ready_timeout_s`` for the build lock: another build held it all along (the
    process is busy, or a build hangs); nothing is wrong with the config that waited."""


class BuildCancelled(RuntimeError):
    """A build waiting for the build lock was no longer wanted (its engine stopped, its head was removed)."""


class BuildLock:
    """Note [One build at a time]: the process's build lock, which knows who holds it and since when."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._holder: tuple[str, str, float] | None = None  # (what builds, its thread's name, since: monotonic)
        self._stepped = 0.0  # when the holder took the lock or last made progress (monotonic)
        self._owner: int | None = None  # the holder's thread

    def holder(self) -> str | None:
        """Who holds the lock now, in words; None when nobody does."""
        h = self._holder
        if h is None:
            return None
        what, thread, since = h
        return f"{what} (thread {thread!r}, for {time.monotonic() - since:.1f} s)"

    @property
    def stepped(self) -> float:
        """When the holder took the lock or last made progress (monotonic; 0: never)."""
        return self._stepped

    def step(self) -> None:
        """Called by the holder, it made progress: a waiter's ``timeout`` counts from now (from anyone else:
        nothing)."""
        if self._owner == threading.get_ident():
            self._stepped = time.monotonic()

    @contextlib.contextmanager
    def held(self, what: str, timeout: float, cancelled: Callable[[], bool] | None = None) -> Iterator[None]:
        """Hold the lock while building ``what``; wait for it while the holder makes progress, at most ``timeout``
        s since its last step (or since this wait began), and not once ``cancelled()`` (then ``BuildCancelled``,
        also when the lock was free: a build nobody wants does not take the lock)."""
        unwanted = cancelled or (lambda: False)
        start = time.monotonic()
        logged = False
        while not self._lock.acquire(timeout=0.25):
            now = time.monotonic()
            waited = now - start
            if unwanted():
                raise BuildCancelled(f"{what}: no longer wanted while waiting to build")
            if now - max(start, self._stepped) >= timeout:
                raise BuildLockTimeout(
                    f"{what}: waited {waited:.1f} s to build while {self.holder() or 'another build'} built, which "
                    f"made no progress for runtime.ready_timeout_s = {timeout:g} s; one model builds at a time in a "
                    "process (Note [One build at a time]), and a build holds its turn until it returns, even one a "
                    "stopped engine left behind"
                )
            if not logged and waited >= WAIT_LOG_S:
                log.info("%s waits to build: %s is building (one model at a time in a process)", what, self.holder())
                logged = True
        try:
            if unwanted():
                raise BuildCancelled(f"{what}: no longer wanted when its turn to build came")
            self._holder = (what, threading.current_thread().name, time.monotonic())
            self._owner = threading.get_ident()
            self.step()
            yield
        finally:
            self._holder = self._owner = None
            self._lock.release()


build_lock = BuildLock()


def frame_spec(cfg: EngineConfig) -> SpecDict:
    """What the foundation model reads: one frame of the configured input size and dtype."""
    return {"frame": TensorSpec((cfg.input.height, cfg.input.width, 3), cfg.input.dtype)}


def build_model(
    cfg: EngineConfig,
    name: str,
    role: Role,
    upstream: SpecDict,
    upstream_meta: dict[str, Any],
    device: torch.device,
    plan_only: bool,
    cancelled: Callable[[], bool] | None = None,
) -> Model:
    """Build one recipe. With ``plan_only`` it lands on the meta device with no weights (for planning).

    Note [One build at a time]: waits for the process's build lock while its holder makes progress, at most the
    config's ``runtime.ready_timeout_s`` after its last step, and not once ``cancelled()``.
    """
    mcfg = cfg.model(name)
    try:
        cls, defaults = resolve(mcfg.model, role)
    except ModelBuildError as e:
        if e.__cause__ is not None:  # the user's module failed as it was imported: its traceback says where
            raise
        raise ModelBuildError(f"{cfg.model_path(name)}.model: {e}") from None  # which field names the model
    ctx = BuildContext(role, name, mcfg, cfg, upstream, upstream_meta, device, plan_only, defaults)
    what = f"model {name!r} of engine {cfg.name!r}"
    where = f"{ctx.where} ({mcfg.model})"
    with build_lock.held(what, cfg.runtime.ready_timeout_s, cancelled), torch.device("meta" if plan_only else device):
        try:
            model = cls.from_config(ctx)
        except ModelBuildError:
            raise
        except Exception as e:  # a user class's own error: which model raised it, and its traceback
            raise ModelBuildError(f"{where}: building it raised {type(e).__name__}: {e}") from e
    if not isinstance(model, Model):
        raise ModelBuildError(f"{where}: from_config returned a {type(model).__name__}, not the model built")
    if not all(isinstance(getattr(model, a, None), dict) for a in ("input_spec", "output_spec", "meta")):
        raise ModelBuildError(
            f"{where}: the model built has no input_spec, output_spec and meta; does its __init__ call "
            "super().__init__() first?"
        )
    given = getattr(mcfg, "postprocess", None)
    if plan_only and given and not ctx.postprocess_read:  # said once, while planning: nothing lost silently
        log.warning(
            "%s: postprocess %s is set, but model %r reads no postprocess options (of the zoo's, the depth heads do): it is "
            "ignored",
            name,
            sorted(given),
            mcfg.model,
        )
    if not plan_only:
        model.load_checkpoint(ctx)
        model.eval().requires_grad_(False)
    return model
