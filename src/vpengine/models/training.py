"""Training a Faster R-CNN detection head on frozen foundation-model features (``vpengine train detector``).

Only the head learns. The foundation model of the config (built exactly as the engine builds it, on the config's
device) runs once per image, and its features are cached in host memory for every epoch; that is what makes
training on a laptop CPU or a Jetson practical. Every image is resized to the config's input size first, because
that is the frame size the engine will see (images of another aspect ratio are squashed the same way, with their
boxes). Classes come from the COCO categories, in category-id order.

The head trained is the config's Faster R-CNN head (``head`` picks one if there are several); a config without
one gets ``frcnn_dinov2`` named ``det`` (or ``frcnn`` if that name is taken). Written next to the checkpoint:
``<stem>.train.json`` (losses per epoch, classes, options, and the ``heads:`` entry that runs the result). Training
never reads the head's configured ``checkpoint`` (``init`` starts from one). Run the result with
``weights.random_weights`` off: that switch applies to every model and would replace the trained weights too.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from safetensors.torch import save_file
from tqdm import tqdm

from vpengine.config import load_config
from vpengine.models.base import BuildContext
from vpengine.models.build import build_model, frame_spec
from vpengine.models.detection import FasterRCNNHead
from vpengine.models.registry import resolve
from vpengine.models.weights import apply_state_dict, read_state_dict

log = logging.getLogger("vpengine.train")

DEFAULT_HEAD_RECIPE = "frcnn_dinov2"

#: Called after each epoch with (epoch, epochs, mean total loss, mean of each loss term).
EpochCallback = Callable[[int, int, float, dict[str, float]], None]


# ------------------------------------------------------------------------------------------------ data
@dataclass
class Sample:
    """One training image: its file, and its boxes (x1, y1, x2, y2 in the file's pixels) and 0-based labels."""

    path: Path
    boxes: np.ndarray  # float32[n, 4]
    labels: np.ndarray  # int64[n]


#: Suffixes of files that are no checkpoint: an --out named so is a slip (a .pth, .pt, .bin or .ckpt is a PyTorch file)
_NOT_CHECKPOINTS = (".onnx", ".json", ".yaml", ".yml", ".npz", ".npy", ".png", ".jpg", ".txt")


def _writable_out(given: str | Path) -> Path:
    """``given`` as a checkpoint file to write, checked before any work: not a folder, not named like another kind
    of file, and in a folder that is or can be made writable. ValueError naming the path otherwise. Nothing is made
    here: a run refused later leaves no folder behind."""
    out = Path(given)
    if out.is_dir() or str(given).endswith(("/", os.sep)):
        raise ValueError(
            f"--out {str(given)!r} is a folder; name the checkpoint file to write, e.g. {str(out / 'head.pth')!r}"
        )
    if out.suffix.lower() in _NOT_CHECKPOINTS:
        raise ValueError(
            f"--out {str(out)!r}: a checkpoint is written as .safetensors or as a PyTorch file (.pth, .pt); name it so"
        )
    folder = out.parent.absolute()
    while not folder.exists():  # the nearest folder that exists: where the missing ones would be made
        folder = folder.parent
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"--out {str(out)!r} cannot be written: {str(folder)!r} is not a writable folder")
    return out


def load_coco(annotations: str | Path, images: str | Path) -> tuple[list[str], list[Sample]]:
    """Class names (in category-id order) and one :class:`Sample` per image of a COCO detection file.

    Crowd annotations are skipped (as COCO training does); images without boxes stay, as negatives.
    """
    path, root = Path(annotations), Path(images)
    if path.is_dir():
        raise FileNotFoundError(f"annotations {str(path)!r} is a folder; give the COCO JSON file in it")
    if not path.is_file():
        raise FileNotFoundError(f"annotations {str(path)!r} do not exist")
    if not root.is_dir():
        raise FileNotFoundError(f"image folder {str(root)!r} does not exist")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"annotations {str(path)!r} are not valid JSON: {e}") from None
    if not isinstance(data, dict):
        raise ValueError(f"annotations {str(path)!r} are not COCO detection JSON (top level is not an object)")
    missing = [k for k in ("images", "annotations", "categories") if not isinstance(data.get(k), list)]
    if missing:
        raise ValueError(f"annotations {str(path)!r} are not COCO detection JSON: no list {missing}")
    for section, keys in (("categories", ("id", "name")), ("images", ("id", "file_name"))):
        for i, entry in enumerate(data[section]):
            if not isinstance(entry, dict) or any(k not in entry for k in keys):
                raise ValueError(f"{path.name}: {section}[{i}] = {entry!r} lacks one of {list(keys)}")
    cats = sorted(data["categories"], key=lambda c: c["id"])
    if not cats:
        raise ValueError(f"annotations {str(path)!r} define no categories")
    ids = [c["id"] for c in cats]  # two categories of one id: every box of it would be trained as the other class
    twice = sorted({str(v) for v in ids if ids.count(v) > 1})
    if twice:
        raise ValueError(f"{path.name}: categories give the id {', '.join(twice)} more than once")
    names_seen = [str(c["name"]) for c in cats]
    same = sorted({n for n in names_seen if names_seen.count(n) > 1})
    if same:  # labels follow ids, so training is right; the detections' names would not tell the classes apart
        log.warning("%s: categories give the name %s to more than one id", path.name, ", ".join(same))
    names = [str(c["name"]) for c in cats]
    label_of = {c["id"]: i for i, c in enumerate(cats)}
    per_image: dict[Any, list[tuple[list[float], int]]] = {im["id"]: [] for im in data["images"]}
    for a in data["annotations"]:
        if a.get("iscrowd", 0):
            continue
        if a.get("image_id") not in per_image:
            raise ValueError(f"{path.name}: annotation {a.get('id')} refers to unknown image_id {a.get('image_id')}")
        if a.get("category_id") not in label_of:
            raise ValueError(
                f"{path.name}: annotation {a.get('id')} has category_id {a.get('category_id')}; "
                f"categories are {sorted(label_of)}"
            )
        bbox = a.get("bbox")
        if not (isinstance(bbox, list) and len(bbox) == 4 and all(isinstance(v, (int, float)) for v in bbox)):
            raise ValueError(f"{path.name}: annotation {a.get('id')} bbox {bbox!r} is not [x, y, w, h]")
        if not all(math.isfinite(v) for v in bbox) or bbox[2] < 0 or bbox[3] < 0:  # 0: dropped and counted below
            raise ValueError(
                f"{path.name}: annotation {a.get('id')} bbox {bbox!r} is not [x, y, w, h] with a width and height of "
                "0 or more (COCO's boxes are x, y, width, height, not two corners)"
            )
        per_image[a["image_id"]].append((bbox, label_of[a["category_id"]]))
    samples = []
    for im in data["images"]:
        file = root / im["file_name"]
        if not file.is_file():
            raise FileNotFoundError(f"{path.name}: image {im['file_name']!r} not found in {str(root)!r}")
        if not cv2.haveImageReader(str(file)):  # its header, now: not after hours of the earlier images' features
            raise ValueError(f"{path.name}: image {im['file_name']!r} is no image OpenCV reads ({str(file)!r})")
        anns = per_image[im["id"]]
        boxes = np.array([[x, y, x + w, y + h] for (x, y, w, h), _ in anns], dtype=np.float32).reshape(-1, 4)
        labels = np.array([lab for _, lab in anns], dtype=np.int64)
        samples.append(Sample(file, boxes, labels))
    if not samples:
        raise ValueError(f"annotations {str(path)!r} list no images")
    return names, samples


def read_frame(path: Path, height: int, width: int, color: str, dtype: str) -> tuple[np.ndarray, float, float]:
    """The image as the engine would receive it (``height`` x ``width``, channel order and dtype of the config),
    and the x and y factors from file pixels to frame pixels."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)  # BGR uint8, whatever the file held
    if img is None:
        raise ValueError(f"cannot read image {str(path)!r}")
    h0, w0 = img.shape[:2]
    if (h0, w0) != (height, width):
        shrink = h0 * w0 > height * width
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    if color == "rgb":
        img = img[..., ::-1]
    frame: np.ndarray = np.ascontiguousarray(img)
    if dtype == "float32":
        frame = frame.astype(np.float32) / 255.0
    return frame, width / w0, height / h0


# ------------------------------------------------------------------------------------------------ config
def _select_head(raw: dict[str, Any], head: str | None, class_names: list[str]) -> str:
    """Pick (or add) the detection head to train in the raw config and give it the dataset's classes."""
    heads = raw.setdefault("heads", [])
    if head is not None:
        entry = next((h for h in heads if h.get("name") == head), None)
        if entry is None:
            raise ValueError(f"--head {head!r}: the config has no such head; heads: {[h.get('name') for h in heads]}")
        cls, _ = resolve(entry["model"], "head")
        if not issubclass(cls, FasterRCNNHead):
            raise ValueError(f"--head {head!r} is a {entry['model']!r} head, not a Faster R-CNN head")
    else:
        found = [h for h in heads if issubclass(resolve(h["model"], "head")[0], FasterRCNNHead)]
        if len(found) > 1:
            raise ValueError(
                f"the config has several detection heads {[h['name'] for h in found]}; pick one with --head"
            )
        if found:
            entry = found[0]
        else:
            taken = {h.get("name") for h in heads}
            name = next((n for n in ("det", "frcnn", "frcnn_det") if n not in taken), None)
            if name is None:
                raise ValueError("the config has no Faster R-CNN head; add one (e.g. model: frcnn_dinov2)")
            entry = {"name": name, "model": DEFAULT_HEAD_RECIPE}
            heads.append(entry)
    opts = entry.setdefault("options", {})
    given_names, given_n = opts.get("class_names"), opts.get("num_classes")
    if given_names is not None and list(given_names) != class_names:
        raise ValueError(
            f"head {entry['name']!r} has class_names {given_names} but the annotations define {class_names}"
        )
    if given_n is not None and given_n != len(class_names):
        raise ValueError(
            f"head {entry['name']!r} has num_classes {given_n} but the annotations define {len(class_names)}: "
            f"{class_names}"
        )
    opts["num_classes"] = len(class_names)
    opts["class_names"] = class_names
    entry["checkpoint"] = None  # training starts from random weights or --init, never from the config's file
    return str(entry["name"])


# ------------------------------------------------------------------------------------------------ training
@contextlib.contextmanager
def _cpu_threads(n: int | None) -> Iterator[None]:
    """PyTorch's intra-op CPU threads set to ``n`` for the block (None: unchanged), restored afterwards."""
    saved = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(saved)


def train_detector(
    config: Any,
    images: str | Path,
    annotations: str | Path,
    out: str | Path,
    *,
    head: str | None = None,
    epochs: int = 12,
    lr: float = 1e-4,
    weight_decay: float = 1e-4,
    batch_size: int = 4,
    hflip: bool = False,
    init: str | Path | None = None,
    seed: int = 0,
    overrides: list[str] | None = None,
    progress: bool = True,
    threads: int | None = None,
    on_epoch: EpochCallback | None = None,
) -> dict[str, Any]:
    """Train the config's Faster R-CNN head on ``images`` + COCO ``annotations``; write the checkpoint ``out``.

    Returns the summary also written to ``<out stem>.train.json``: ``epoch_loss`` (mean total loss per epoch),
    ``epoch_losses`` (each loss term per epoch), ``class_names``, ``head_config`` (the ``heads:`` entry to run it),
    ``interrupted_after`` (None). A KeyboardInterrupt (Ctrl-C) after an epoch has finished writes that epoch's head
    and summary (``interrupted_after``: its number) and raises :class:`TrainingInterrupted`, a KeyboardInterrupt
    carrying the summary; one before writes nothing and goes on as it came. The files are replaced whole, never
    left half-written.
    ``config`` is an engine config or anything ``load_config`` accepts, with ``overrides`` applied; ``threads`` sets
    PyTorch's CPU threads for the duration of the call; ``progress`` shows progress bars; ``on_epoch`` is called
    after every epoch.
    """
    if epochs < 1 or batch_size < 1 or not lr > 0:
        raise ValueError(f"epochs ({epochs}) and batch_size ({batch_size}) must be >= 1 and lr ({lr}) > 0")
    if not (math.isfinite(weight_decay) and weight_decay >= 0):
        raise ValueError(f"weight_decay must be a number >= 0, got {weight_decay}")
    out = _writable_out(out)  # before any work: a run of hours must not end on a path it cannot write
    class_names, samples = load_coco(annotations, images)
    raw = load_config(config, overrides).model_dump(mode="json")
    head_name = _select_head(raw, head, class_names)
    cfg = load_config(raw)
    hcfg = cfg.head(head_name)
    device = torch.device(cfg.device)

    with _cpu_threads(threads):
        t0 = time.monotonic()
        fm = build_model(cfg, "foundation", "foundation", frame_spec(cfg), {}, device, plan_only=False)
        cls, defaults = resolve(hcfg.model, "head")
        ctx = BuildContext("head", head_name, hcfg, cfg, fm.output_spec, dict(fm.meta), device, False, defaults)
        model = cls.from_config(ctx)  # random weights from the head's own `seed` option
        assert isinstance(model, FasterRCNNHead)
        if init is not None:
            what = f"{head_name} ({hcfg.model}, {model.describe()})"
            apply_state_dict(model, read_state_dict(init), str(init), what)
        tokens, targets, dropped = _cache_features(fm, model.layer, samples, cfg, device, hflip, progress)
        del fm  # only the cached features are needed from here on
        t_features = time.monotonic() - t0
        t1 = time.monotonic()
        epoch_loss, epoch_terms, interrupted = _fit(
            model, tokens, targets, device, epochs, lr, weight_decay, batch_size, seed, progress, on_epoch
        )
        t_train = time.monotonic() - t1

    out.parent.mkdir(parents=True, exist_ok=True)
    sd = {k: v.detach().to("cpu").contiguous() for k, v in model.state_dict().items()}
    if out.suffix == ".safetensors":
        _replace(
            out,
            lambda p: save_file(sd, str(p), metadata={"vpengine": "frcnn head", "classes": json.dumps(class_names)}),
        )
    else:
        _replace(out, lambda p: torch.save(sd, str(p)))

    options = dict(hcfg.options)
    backbone = ctx.upstream_meta.get("backbone")
    if backbone:
        options["trained_on"] = backbone
    head_config = {
        "name": head_name,
        "model": hcfg.model,
        "checkpoint": str(out.resolve()),
        "options": options,
    }
    summary = {
        "checkpoint": str(out),
        "backbone": backbone,
        "images": len(samples),
        "samples": len(tokens),
        "boxes_dropped": dropped,
        "class_names": class_names,
        "epochs": epochs,
        "lr": lr,
        "weight_decay": weight_decay,
        "batch_size": batch_size,
        "hflip": hflip,
        "seed": seed,
        "device": str(device),
        "feature_s": t_features,
        "train_s": t_train,
        "epoch_loss": epoch_loss,
        "epoch_losses": epoch_terms,
        "interrupted_after": len(epoch_loss) if interrupted else None,
        "head_config": head_config,
    }
    _replace(out.parent / f"{out.stem}.train.json", lambda p: p.write_text(json.dumps(summary, indent=2)))
    if interrupted:
        raise TrainingInterrupted(summary)
    return summary


class TrainingInterrupted(KeyboardInterrupt):
    """A Ctrl-C that ended a training after an epoch had finished: that epoch's head and summary were written."""

    def __init__(self, summary: dict[str, Any]) -> None:
        super().__init__(f"interrupted after epoch {summary['interrupted_after']}")
        self.summary = summary


def _replace(path: Path, write: Callable[[Path], Any]) -> None:
    """``write`` into a file beside ``path``, then rename it over ``path``: a reader (or a Ctrl-C) never sees half."""
    part = path.with_name(f".{path.name}.part")
    try:
        write(part)
        os.replace(part, path)
    finally:
        part.unlink(missing_ok=True)


def _cache_features(
    fm: Any,
    layer: str,
    samples: list[Sample],
    cfg: Any,
    device: Any,
    hflip: bool,
    progress: bool,
) -> tuple[list[Any], list[dict[str, Any]], int]:
    """Run the frozen foundation model once per image (and its mirror image with ``hflip``).

    Returns the ``layer`` tokens per image on the host, targets with boxes in input-frame pixels, and how many
    boxes were dropped for being under a pixel at the input size. Recomputing every epoch would give the same
    features: the foundation model never changes.
    """
    h, w = cfg.input.height, cfg.input.width
    tokens: list[torch.Tensor] = []
    targets: list[dict[str, torch.Tensor]] = []
    dropped = 0
    variants = (False, True) if hflip else (False,)
    bar = tqdm(total=len(samples) * len(variants), desc="features", unit="img", disable=not progress)
    with bar, torch.inference_mode():  # closed on a Ctrl-C too: what is printed next starts on a line of its own
        for s in samples:
            frame, fx, fy = read_frame(s.path, h, w, cfg.input.color, cfg.input.dtype)
            boxes = s.boxes * np.array([fx, fy, fx, fy], dtype=np.float32)
            boxes = np.clip(boxes, 0, [w, h, w, h]).astype(np.float32)
            keep = ((boxes[:, 2] - boxes[:, 0]) >= 1) & ((boxes[:, 3] - boxes[:, 1]) >= 1)
            dropped += int((~keep).sum())
            boxes, labels = boxes[keep], s.labels[keep]
            for flip in variants:
                f, b = frame, boxes
                if flip:
                    f = np.ascontiguousarray(frame[:, ::-1])
                    b = np.stack([w - boxes[:, 2], boxes[:, 1], w - boxes[:, 0], boxes[:, 3]], 1)
                feats = fm({"frame": torch.from_numpy(f).to(device)[None]})  # a batch of one frame
                tokens.append(feats[layer].to("cpu", copy=True))  # [1, h*w, C]: torch.cat makes batches
                targets.append(
                    {
                        "boxes": torch.from_numpy(b.reshape(-1, 4).copy()),
                        "labels": torch.from_numpy(labels.copy()),
                    }
                )
                bar.update(1)
    if dropped:
        log.warning("%d boxes smaller than one pixel at %dx%d were dropped", dropped, w, h)
    return tokens, targets, dropped


def _fit(
    model: Any,
    tokens: list[Any],
    targets: list[dict[str, Any]],
    device: Any,
    epochs: int,
    lr: float,
    weight_decay: float,
    batch_size: int,
    seed: int,
    progress: bool,
    on_epoch: EpochCallback | None,
) -> tuple[list[float], list[dict[str, float]], bool]:
    """AdamW with linear warm-up and cosine decay over cached features; mean losses per epoch, and whether a
    KeyboardInterrupt ended it after an epoch had finished: the model then holds that epoch's weights (hours of
    training are not lost to a Ctrl-C; one before the first epoch's end is raised)."""
    n = len(tokens)
    steps_per_epoch = math.ceil(n / batch_size)
    total_steps = epochs * steps_per_epoch
    warmup = max(1, min(500, total_steps // 10))

    def lr_factor(step: int) -> float:
        # linear warm-up (a fresh RPN can blow up at full rate), then cosine decay to zero
        if step < warmup:
            return (step + 1) / warmup
        return 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, total_steps - warmup)))

    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_factor)
    epoch_loss: list[float] = []
    epoch_terms: list[dict[str, float]] = []
    finished: tuple[int, dict[str, Any]] | None = None  # the last finished epoch and its weights, set at once
    model.train()
    try:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)  # the order of images and torchvision's anchor/proposal sampling
            for epoch in range(1, epochs + 1):
                order = torch.randperm(n).tolist()
                sums: dict[str, float] = {}
                bar = tqdm(
                    range(steps_per_epoch),
                    desc=f"epoch {epoch}/{epochs}",
                    unit="step",
                    disable=not progress,
                    leave=False,
                )
                for step in bar:
                    idx = order[step * batch_size : (step + 1) * batch_size]
                    batch = torch.cat([tokens[i] for i in idx]).to(device)
                    tgt = [{k: v.to(device) for k, v in targets[i].items()} for i in idx]
                    losses = model.losses(batch, tgt)
                    loss = torch.stack(list(losses.values())).sum()
                    if not torch.isfinite(loss):
                        terms = {k: round(v.item(), 4) for k, v in losses.items()}
                        raise RuntimeError(
                            f"loss became {loss.item()} at epoch {epoch} step {step + 1} ({terms}); "
                            f"try a lower --lr than {lr}"
                        )
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    torch.nn.utils.clip_grad_norm_(params, 10.0)
                    opt.step()
                    sched.step()
                    for k, v in losses.items():
                        sums[k] = sums.get(k, 0.0) + v.item() * len(idx)
                    sums["loss"] = sums.get("loss", 0.0) + loss.item() * len(idx)
                    bar.set_postfix(loss=f"{loss.item():.3f}", lr=f"{sched.get_last_lr()[0]:.2e}")
                bar.close()
                means = {k: v / n for k, v in sums.items()}
                epoch_loss.append(means.pop("loss"))
                epoch_terms.append(means)
                finished = (epoch, {k: v.detach().clone() for k, v in model.state_dict().items()})
                if on_epoch is not None:
                    on_epoch(epoch, epochs, epoch_loss[-1], means)
    except KeyboardInterrupt:
        if finished is None:
            raise
        done, weights = finished
        del epoch_loss[done:], epoch_terms[done:]  # an interrupt may come between an epoch's losses and its weights
        model.load_state_dict(weights)  # a step of the epoch it ended may have run: the finished one's weights
        model.eval()
        return epoch_loss, epoch_terms, True
    model.eval()
    return epoch_loss, epoch_terms, False
