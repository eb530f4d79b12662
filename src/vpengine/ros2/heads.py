"""Heads added and removed from ROS 2: the commands, their outcomes, and the thread that carries them out.

A transport receives ``add_head`` (the head's config, YAML or JSON text, as under ``heads:`` in a config file) and
``remove_head`` (a head's name) commands, hands them to :class:`HeadCommands`, and publishes each
:class:`HeadOutcome` it gets back (``<ns>/head_events``). What a command changes (the engine's heads, the output
topics, the model names) is decided by :meth:`vpengine.ros2.core.Ros2Core.add_head` and ``remove_head``. No
middleware here.

Note [Head commands]
~~~~~~~~~~~~~~~~~~~~
Adding a head builds and warms it up (seconds; ``Engine.add_head``). On the control thread (Note [Control path] in
:mod:`vpengine.ros2.control`) that would hold rate and priority commands and /diagnostics as long, so the control
thread only queues head commands, and one thread of their own takes them one at a time, in the order they came
(the engine adds or removes one head at a time anyway; one after another, a remove sent after an add finds the head).
Every command has an outcome, success or the engine's error, published on ``<ns>/head_events`` (topics have no reply
channel), logged, and counted in /diagnostics; a failed command leaves the engine and the topics as they were.
An added head's topics are opened before its outputs are routed to them (the few it may give in between, as the
engine attaches it before the interface learns of it, are not published); a removed head's outputs stop being
routed before its topics are closed, and an output already on its way to a closed topic is dropped by the
transport, not published.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import yaml

if TYPE_CHECKING:
    from vpengine.ros2.outputs import OutputTopic

log = logging.getLogger("vpengine.ros2")

#: The command kinds, as the control loop receives them (the topics ``<ns>/add_head`` and ``<ns>/remove_head``).
HEAD_COMMANDS = ("add_head", "remove_head")

#: What the engine raises for a head command it refuses (and then nothing changed): a bad config (ConfigError, or
#: text that is not YAML at all), a name taken, an unknown head, the last head (ValueError, KeyError), no seat free,
#: a failed build, a stopped engine (RuntimeError).
REFUSALS = (ValueError, KeyError, RuntimeError, yaml.YAMLError)

#: What a transport does with an added (removed) head's output topics: create (close) their publishers.
TopicsHook = Callable[[list["OutputTopic"]], None]


@dataclass(frozen=True)
class HeadOutcome:
    """What one head command did; :meth:`text` is the ``<ns>/head_events`` message."""

    #: add_head | remove_head
    command: str
    #: the head's name (for an add whose config names none: None)
    head: str | None
    ok: bool
    #: what happened, or the engine's error (naming the bad value)
    message: str
    #: the output topics opened (add) or closed (remove)
    topics: tuple[str, ...] = ()
    #: the models after the command (``<ns>/model_names``)
    model_names: tuple[str, ...] = ()

    def text(self) -> str:
        """JSON: ``{"command", "head", "ok", "message", "topics", "model_names"}``."""
        return json.dumps(
            {
                "command": self.command,
                "head": self.head,
                "ok": self.ok,
                "message": self.message,
                "topics": list(self.topics),
                "model_names": list(self.model_names),
            }
        )


def named_in(config_text: str) -> str | None:
    """The head's name in an add command's config text, to label its outcome; None when there is none to read
    (the engine names what is wrong with the text)."""
    try:
        data = yaml.safe_load(config_text)
    except yaml.YAMLError:
        return None
    name = data.get("name") if isinstance(data, dict) else None
    return name if isinstance(name, str) else None


def error_text(e: BaseException) -> str:
    """An engine error as the outcome's message (a KeyError's text without its quotes)."""
    return str(e.args[0]) if isinstance(e, KeyError) and e.args else str(e)


class Changes(Protocol):
    """What :class:`HeadCommands` uses of :class:`vpengine.ros2.core.Ros2Core`."""

    def add_head(self, config_text: str, open_topics: TopicsHook) -> HeadOutcome: ...

    def remove_head(self, name: str, close_topics: TopicsHook) -> HeadOutcome: ...


class HeadCommands:
    """Note [Head commands]: head commands, one at a time, on a thread of their own (:meth:`run`).

    ``put`` queues a command and returns at once with a future of its outcome (a service waits on it; the topics
    do not). Each outcome is handed to ``publish`` (the transport: ``<ns>/head_events``, ``<ns>/model_names``,
    /diagnostics) on this thread, after it is logged.
    """

    def __init__(
        self,
        core: Changes,
        open_topics: TopicsHook,
        close_topics: TopicsHook,
        publish: Callable[[HeadOutcome], None],
    ) -> None:
        self.core, self.open_topics, self.close_topics, self.publish = core, open_topics, close_topics, publish
        self._queue: queue.SimpleQueue[tuple[str, str, Future[HeadOutcome]]] = queue.SimpleQueue()

    def put(self, kind: str, text: str) -> Future[HeadOutcome]:
        """Queue ``add_head`` (``text``: the head's config) or ``remove_head`` (``text``: its name)."""
        if kind not in HEAD_COMMANDS:
            raise ValueError(f"head command {kind!r} is not known; accepted: {', '.join(HEAD_COMMANDS)}")
        done: Future[HeadOutcome] = Future()
        self._queue.put((kind, text, done))
        return done

    def run(self, stop: threading.Event) -> None:
        """Until ``stop`` is set; commands still queued then are answered as not carried out."""
        while not stop.is_set():
            try:
                kind, text, done = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            done.set_result(self.apply(kind, text))
        while True:
            try:
                kind, text, done = self._queue.get_nowait()
            except queue.Empty:
                return
            head = named_in(text) if kind == "add_head" else text.strip()
            done.set_result(HeadOutcome(kind, head, False, "the interface is stopping"))

    def apply(self, kind: str, text: str) -> HeadOutcome:
        """Carry out one command now (on the calling thread), log its outcome and publish it."""
        if kind == "add_head":
            out = self.core.add_head(text, self.open_topics)
        else:
            out = self.core.remove_head(text, self.close_topics)
        if out.ok:
            log.info("%s: %s", kind, out.message)
        else:
            log.warning("%s refused: %s", kind if out.head is None else f"{kind} {out.head!r}", out.message)
        self.publish(out)
        return out


def opened_text(head: str, topics: Sequence[str]) -> str:
    """The message of a head added: its name and its topics."""
    return f"head {head!r} added; " + (
        f"publishing on {', '.join(topics)}" if topics else "it has no ROS 2 message mapping: nothing published"
    )
