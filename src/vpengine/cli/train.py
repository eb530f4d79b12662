"""``vpengine train detector``: train a Faster R-CNN head on frozen foundation-model features.

::

    vpengine train detector --config CONFIG --images DIR --annotations COCO.json --out head.pth [--epochs 12 ...]

The training itself is ``vpengine.models.training.train_detector``; this command parses its arguments, prints a
line per epoch and, at the end, the ``heads:`` entry that runs the result. Ctrl-C after an epoch has finished writes
that epoch's head and exits 130; before, it writes nothing and says so.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from vpengine.arguments import add_overrides_argument


def _positive(kind: type, name: str) -> Any:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a {kind.__name__}, got {text!r}") from None
        if not value > 0 or (kind is float and not math.isfinite(value)):
            raise argparse.ArgumentTypeError(f"{name} must be a positive {kind.__name__}, got {text!r}")
        return value

    return parse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", choices=["detector"], help="what to train: detector (Faster R-CNN head on frozen features)")
    p.add_argument("--config", "-c", required=True, help="engine config (its foundation model and head)")
    p.add_argument("--images", required=True, help="folder the COCO file_name entries are relative to")
    p.add_argument("--annotations", required=True, help="COCO-format JSON with boxes (bbox: x, y, w, h)")
    p.add_argument("--out", "-o", required=True, help="checkpoint to write (.pth, or .safetensors)")
    p.add_argument("--head", help="name of the head to train when the config has several detection heads")
    p.add_argument("--epochs", type=_positive(int, "--epochs"), default=12, help="passes over the data (12)")
    p.add_argument("--lr", type=_positive(float, "--lr"), default=1e-4, help="AdamW peak learning rate (1e-4)")
    p.add_argument("--weight-decay", type=float, default=1e-4, help="AdamW weight decay (1e-4)")
    p.add_argument("--batch-size", type=_positive(int, "--batch-size"), default=4, help="images per step (4)")
    p.add_argument(
        "--hflip",
        action="store_true",
        help="also train on mirrored images (their features are computed too, so caching takes twice as long)",
    )
    p.add_argument("--init", help="start from this head checkpoint instead of random weights")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the image order and of anchor/proposal sampling (initial weights: the head's seed option)",
    )
    add_overrides_argument(p, "heads.det.options.out_channels=128")
    p.add_argument("--device", help="override the config's device (cpu, cuda, cuda:N)")
    p.add_argument(
        "--threads",
        type=_positive(int, "--threads"),
        help="PyTorch CPU threads while training (default: PyTorch's; 1 is faster on a busy machine)",
    )
    p.add_argument(
        "--random-weights",
        action="store_true",
        help="random foundation-model weights (smoke tests only: the head learns nothing useful)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars (epoch lines still print)")


def _print_epoch(epoch: int, epochs: int, loss: float, terms: dict[str, float]) -> None:
    parts = " ".join(f"{k.removeprefix('loss_')}={v:.3f}" for k, v in terms.items())
    print(f"epoch {epoch}/{epochs}: loss {loss:.4f} ({parts})", flush=True)


def main(args: argparse.Namespace) -> int:
    import yaml

    from vpengine.models.training import TrainingInterrupted, train_detector

    overrides = list(args.overrides)
    if args.device:
        overrides.append(f"device={args.device}")
    if args.random_weights:
        overrides.append("weights.random_weights=true")
    try:
        s = train_detector(
            args.config,
            args.images,
            args.annotations,
            args.out,
            head=args.head,
            epochs=args.epochs,
            lr=args.lr,
            weight_decay=args.weight_decay,
            batch_size=args.batch_size,
            hflip=args.hflip,
            init=args.init,
            seed=args.seed,
            overrides=overrides,
            progress=not args.no_progress,
            threads=args.threads,
            on_epoch=_print_epoch,
        )
    except TrainingInterrupted as e:
        s = e.summary
    except KeyboardInterrupt:
        print(
            f"vpengine train detector: interrupted before the first epoch ended: nothing written to {args.out}",
            file=sys.stderr,
        )
        return 130
    stopped = s["interrupted_after"]
    print(
        f"{f'interrupted after epoch {stopped} of {args.epochs}: ' if stopped else ''}trained "
        f"{s['head_config']['name']} on {s['images']} images"
        f"{' and their mirror images' if s['hflip'] else ''} ({len(s['class_names'])} classes) in "
        f"{s['feature_s'] + s['train_s']:.1f} s: loss {s['epoch_loss'][0]:.4f} -> {s['epoch_loss'][-1]:.4f}; "
        f"wrote {s['checkpoint']}{f' (the weights of epoch {stopped})' if stopped else ''}"
    )
    print("run it with this head entry in the config:")
    print(yaml.safe_dump({"heads": [s["head_config"]]}, sort_keys=False), end="")
    return 130 if stopped else 0
