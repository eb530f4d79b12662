"""``vpengine mps start | stop | status``: a CUDA MPS control daemon with a private pipe directory.

Engines find it by themselves (config ``mps: auto``); other shells need
``export CUDA_MPS_PIPE_DIRECTORY=<dir>`` as printed by ``start``.
"""

from __future__ import annotations

import argparse
import json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=["start", "stop", "status"])
    p.add_argument("--pipe-dir", help="pipe directory (default: a private, owner-only one; see `status`)")
    p.add_argument("--json", action="store_true")


def main(args: argparse.Namespace) -> int:
    from vpengine.runtime import mps

    if args.action == "start":
        st = mps.start(args.pipe_dir)
        msg = "started" if st["started"] else "already running"
        print(
            json.dumps(st)
            if args.json
            else f"MPS control daemon {msg} at {st['pipe_directory']}\n"
            f"other shells: export CUDA_MPS_PIPE_DIRECTORY={st['pipe_directory']}"
        )
        return 0
    if args.action == "stop":
        d = args.pipe_dir or mps.find_daemon() or mps.private_pipe_dir()
        stopped = mps.stop(d)
        print(
            json.dumps({"pipe_directory": d, "stopped": stopped})
            if args.json
            else (f"stopped the MPS daemon at {d}" if stopped else f"no MPS daemon answers at {d}")
        )
        return 0
    found = mps.find_daemon(args.pipe_dir)
    st = mps.status(found or args.pipe_dir or mps.candidate_dirs()[0])
    st["searched"] = mps.candidate_dirs(args.pipe_dir)
    if args.json:
        print(json.dumps(st))
    else:
        print(
            f"MPS daemon {'reachable' if st['reachable'] else 'not reachable'} at {st['pipe_directory']}"
            + ("" if st["reachable"] else f" ({st['reason']}); searched: {', '.join(st['searched'])}")
        )
    return 0 if st["reachable"] else 1
