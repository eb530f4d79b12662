"""`vpengine train detector` end to end: synthetic shapes + COCO JSON -> trained head -> engine detections; and the
training library (`vpengine.models.training`) behind it."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

pytestmark = pytest.mark.timeout(240)

CLASSES = ["box", "disc"]
FILE_HW = (240, 320)  # image files: twice the engine's input size, so training must scale boxes
INPUT_HW = (120, 160)


def make_dataset(root: Path, n: int = 8, seed: int = 0) -> tuple[Path, Path, list[list[tuple[list[float], int]]]]:
    """``n`` images of filled rectangles (class 0) and ellipses (class 1) and their COCO JSON.

    Returns the image folder, the JSON path and, per image, its boxes (x1, y1, x2, y2 in file pixels) and labels.
    """
    rng = np.random.default_rng(seed)
    img_dir = root / "images"
    img_dir.mkdir(parents=True)
    fh, fw = FILE_HW
    images, annotations, truth = [], [], []
    for i in range(n):
        img = rng.integers(0, 50, (fh, fw, 3), dtype=np.uint8)
        objects: list[tuple[list[float], int]] = []
        for _ in range(rng.integers(2, 4)):
            for _attempt in range(50):
                bw, bh = (int(v) for v in rng.integers(50, 110, 2))
                x, y = int(rng.integers(0, fw - bw)), int(rng.integers(0, fh - bh))
                box = [x, y, x + bw, y + bh]
                if all(_iou(box, o[0]) == 0 for o in objects):
                    break
            else:
                continue
            label = int(rng.integers(0, 2))
            color = tuple(int(c) for c in rng.integers(120, 256, 3))
            if label == 0:
                cv2.rectangle(img, (x, y), (x + bw - 1, y + bh - 1), color, thickness=-1)
            else:
                cv2.ellipse(img, (x + bw // 2, y + bh // 2), (bw // 2, bh // 2), 0, 0, 360, color, thickness=-1)
            objects.append((box, label))
        name = f"img_{i:02d}.png"
        cv2.imwrite(str(img_dir / name), img)
        images.append({"id": 100 + i, "file_name": name, "width": fw, "height": fh})
        for box, label in objects:
            x1, y1, x2, y2 = box
            annotations.append(
                {
                    "id": len(annotations) + 1,
                    "image_id": 100 + i,
                    "category_id": 7 + label,  # non-contiguous ids: the trainer must map them to 0..K-1
                    "bbox": [x1, y1, x2 - x1, y2 - y1],
                    "area": (x2 - x1) * (y2 - y1),
                    "iscrowd": 0,
                }
            )
        truth.append(objects)
    cats = [{"id": 7 + k, "name": name} for k, name in enumerate(CLASSES)]
    ann = root / "train.json"
    ann.write_text(json.dumps({"images": images, "annotations": annotations, "categories": cats}))
    return img_dir, ann, truth


def _iou(a, b) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


HEAD_OPTIONS = {
    "out_channels": 32,
    "representation_size": 64,
    "rpn_batch_size_per_image": 64,
    "rpn_pre_nms_top_n_train": 300,
    "rpn_post_nms_top_n_train": 200,
    "rpn_pre_nms_top_n_test": 200,
    "rpn_post_nms_top_n_test": 100,
    "box_batch_size_per_image": 64,
    "max_detections": 10,
    "score_threshold": 0.3,
}


def write_config(path: Path) -> Path:
    cfg = {
        "name": "train-test",
        "mode": "thread",
        "device": "cpu",
        "input": {"height": INPUT_HW[0], "width": INPUT_HW[1]},
        "foundation_model": {"model": "tiny_vit", "preprocess": {"resize": "square", "size": 112}},
        "heads": [{"name": "det", "model": "frcnn_dinov2", "options": HEAD_OPTIONS}],
    }
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_train_detector_cli_loss_falls_and_engine_detects_with_the_checkpoint(tmp_path, capsys):
    from vpengine.cli.main import main
    from vpengine.engine import Engine

    img_dir, ann, truth = make_dataset(tmp_path)
    cfg_path = write_config(tmp_path / "train.yaml")
    out = tmp_path / "ckpt" / "head.pth"
    rc = main(
        [
            "train",
            "detector",
            "--config",
            str(cfg_path),
            "--images",
            str(img_dir),
            "--annotations",
            str(ann),
            "--out",
            str(out),
            "--epochs",
            "30",
            "--lr",
            "2e-3",
            "--batch-size",
            "4",
            "--no-progress",
            "--threads",
            "1",  # two OpenMP threads on a busy 2-core machine are many times slower than one
        ]
    )
    printed = capsys.readouterr().out
    assert rc == 0, printed
    assert out.is_file()
    log = json.loads((out.parent / "head.train.json").read_text())
    losses = log["epoch_loss"]
    assert len(losses) == 30 and all(np.isfinite(losses))
    assert losses[-1] < 0.7 * losses[0], losses
    assert log["class_names"] == CLASSES
    assert "epoch 30/30: loss" in printed and "wrote" in printed

    # The checkpoint runs in the engine exactly as the printed head entry says. Preprocessing squashes the 4:3
    # frames to a square, so boxes left in preprocessed pixels would miss the objects: matching the drawn shapes
    # in input pixels checks the whole coordinate path.
    head_cfg = log["head_config"]
    assert head_cfg["checkpoint"] == str(out.resolve()) and head_cfg["options"]["trained_on"] == "tiny_vit"
    assert yaml.safe_load(printed[printed.index("heads:") :]) == {"heads": [head_cfg]}
    cfg = yaml.safe_load(cfg_path.read_text())
    cfg["heads"] = [head_cfg]
    h, w = INPUT_HW
    sx, sy = w / FILE_HW[1], h / FILE_HW[0]
    matched, total = 0, 0
    with Engine(cfg) as engine:
        assert engine.head_info("det")["labels"] == CLASSES
        for i, objects in enumerate(truth):
            frame = cv2.resize(cv2.imread(str(img_dir / f"img_{i:02d}.png")), (w, h), interpolation=cv2.INTER_AREA)
            r = engine.wait(engine.submit(frame), timeout=30)["det"]
            n = r["count"]
            boxes = r["boxes"]
            assert 1 <= n <= HEAD_OPTIONS["max_detections"] and boxes.shape == (n, 4)
            assert np.all(boxes[:, :2] >= 0) and np.all(boxes[:, 2] <= w) and np.all(boxes[:, 3] <= h)
            assert np.all(boxes[:, 2:] > boxes[:, :2])
            assert np.all(np.diff(r["scores"]) <= 0) and np.all(r["scores"] > HEAD_OPTIONS["score_threshold"])
            assert set(r["labels"].tolist()) <= {0, 1}
            for box, _label in objects:
                gt = [box[0] * sx, box[1] * sy, box[2] * sx, box[3] * sy]
                total += 1
                matched += max(_iou(gt, b) for b in boxes.tolist()) >= 0.5
    assert matched >= 0.7 * total, f"{matched} of {total} drawn shapes found (IoU >= 0.5)"


def test_coco_loader_maps_category_ids_to_labels_and_skips_crowd(tmp_path):
    from vpengine.models.training import load_coco

    img_dir, ann, truth = make_dataset(tmp_path, n=3)
    data = json.loads(ann.read_text())
    data["categories"].reverse()  # order in the file does not matter: labels follow category ids
    crowd = {**data["annotations"][0], "id": 999, "iscrowd": 1}
    data["annotations"].append(crowd)
    data["images"].append({"id": 555, "file_name": "img_00.png", "width": 320, "height": 240})  # no boxes
    ann.write_text(json.dumps(data))
    names, samples = load_coco(ann, img_dir)
    assert names == CLASSES
    assert len(samples) == 4 and samples[3].boxes.shape == (0, 4)
    for s, objects in zip(samples, truth):
        np.testing.assert_array_equal(s.boxes, np.array([b for b, _ in objects], np.float32))
        assert s.labels.tolist() == [lab for _, lab in objects]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["annotations"][0].update(category_id=99), "category_id 99"),
        (lambda d: d["images"][0].update(file_name="missing.png"), "missing.png"),
        (lambda d: d["annotations"][0].update(bbox=[1, 2, 3]), "is not [x, y, w, h]"),
        (lambda d: d.pop("categories"), "not COCO detection JSON"),
        (lambda d: d["images"][1].pop("file_name"), "images[1]"),
        # an image no reader takes: found before the features of the others, not after them
        (lambda d: d["images"][1].update(file_name="corrupt.png"), "image 'corrupt.png' is no image OpenCV reads"),
        # two categories of one id: every box of it would be trained as the other class
        (lambda d: d["categories"][1].update(id=d["categories"][0]["id"]), "categories give the id 7 more than once"),
        # corners for width and height, a NaN: refused naming the annotation, not dropped as "smaller than a pixel"
        (lambda d: d["annotations"][0].update(bbox=[100, 100, -50, -50]), "with a width and height of 0 or more"),
        (lambda d: d["annotations"][0].update(bbox=[float("nan"), 1, 2, 3]), "with a width and height of 0 or more"),
    ],
)
def test_train_cli_reports_bad_annotations_by_name(tmp_path, capsys, edit, message):
    from vpengine.cli.main import main

    img_dir, ann, _ = make_dataset(tmp_path, n=2)
    (img_dir / "corrupt.png").write_bytes(b"not an image" * 10)
    data = json.loads(ann.read_text())
    edit(data)
    ann.write_text(json.dumps(data))
    cfg = write_config(tmp_path / "c.yaml")
    args = ["train", "detector", "-c", str(cfg), "--images", str(img_dir), "--annotations", str(ann)]
    assert main([*args, "--out", str(tmp_path / "h.pth")]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "h.pth").exists()


@pytest.mark.parametrize(
    ("out", "message"),
    [
        ("folder", "is a folder; name the checkpoint file to write"),
        ("head.ONNX", "a checkpoint is written as .safetensors or as a PyTorch file (.pth, .pt)"),
        ("file/head.pth", "cannot be written"),
        ("new/", "is a folder; name the checkpoint file to write"),
    ],
)
def test_train_refuses_an_out_it_cannot_write_before_any_work(tmp_path, capsys, monkeypatch, out, message):
    """An --out that is a folder, of a suffix no checkpoint has, or under a file was found after the training (the
    epochs lost, a traceback): refused before the backbone is built."""
    from vpengine.cli.main import main
    from vpengine.models import training

    img_dir, ann, _ = make_dataset(tmp_path, n=2)
    (tmp_path / "folder").mkdir()
    (tmp_path / "file").write_text("")
    monkeypatch.setattr(training, "load_coco", lambda *a: pytest.fail("reached the dataset"))
    cfg = write_config(tmp_path / "c.yaml")
    args = ["train", "detector", "-c", str(cfg), "--images", str(img_dir), "--annotations", str(ann)]
    given = str(tmp_path / out) + ("/" if out.endswith("/") else "")
    assert main([*args, "--out", given]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "new").exists()  # nothing made for a refused run


def test_train_refuses_a_head_whose_classes_differ_from_the_annotations(tmp_path):
    from vpengine.models.training import train_detector

    img_dir, ann, _ = make_dataset(tmp_path, n=2)
    cfg = write_config(tmp_path / "c.yaml")
    with pytest.raises(ValueError, match=r"class_names \['cat', 'dog'\] but the annotations define \['box', 'disc'\]"):
        train_detector(cfg, img_dir, ann, tmp_path / "h.pth", overrides=["heads.det.options.class_names=[cat, dog]"])


def test_the_training_api_reports_each_epoch_to_its_caller_and_prints_nothing(tmp_path, capsys):
    from vpengine.models.training import train_detector

    img_dir, ann, _ = make_dataset(tmp_path, n=2)
    cfg = write_config(tmp_path / "c.yaml")
    seen: list[tuple[int, int, float, dict[str, float]]] = []
    summary = train_detector(
        cfg,
        img_dir,
        ann,
        tmp_path / "h.pth",
        epochs=2,
        batch_size=2,
        progress=False,
        threads=1,
        on_epoch=lambda *a: seen.append(a),
    )
    assert [(e, n) for e, n, _, _ in seen] == [(1, 2), (2, 2)]
    assert [loss for _, _, loss, _ in seen] == summary["epoch_loss"]
    assert [terms for _, _, _, terms in seen] == summary["epoch_losses"]
    assert capsys.readouterr().out == ""  # printing is the command's job
    assert (tmp_path / "h.pth").is_file() and (tmp_path / "h.train.json").is_file()


def test_ctrl_c_during_training_writes_the_last_finished_epochs_head_and_says_so(tmp_path, capsys, monkeypatch):
    from vpengine.cli.main import main
    from vpengine.models.detection import FasterRCNNHead

    img_dir, ann, _ = make_dataset(tmp_path, n=4)
    cfg = write_config(tmp_path / "c.yaml")
    out = tmp_path / "h.pth"
    args = ["train", "detector", "-c", str(cfg), "--images", str(img_dir), "--annotations", str(ann), "--out",
            str(out), "--epochs", "5", "--batch-size", "2", "--no-progress", "--threads", "1"]  # fmt: skip
    real = FasterRCNNHead.losses
    calls: list[int] = []
    after_two: dict[str, torch.Tensor] = {}

    def losses(self, *a, **k):  # two steps an epoch: Ctrl-C at the second step of epoch 3
        calls.append(1)
        if len(calls) == 5:  # epoch 3's first step: the weights are still epoch 2's
            after_two.update({k: v.detach().clone() for k, v in self.state_dict().items()})
        if len(calls) == 6:
            raise KeyboardInterrupt
        return real(self, *a, **k)

    monkeypatch.setattr(FasterRCNNHead, "losses", losses)
    assert main(args) == 130
    printed = capsys.readouterr().out
    assert "epoch 2/5: loss" in printed and "epoch 3/5" not in printed
    assert "interrupted after epoch 2 of 5: trained det" in printed and "(the weights of epoch 2)" in printed
    saved = torch.load(out, weights_only=True)
    assert saved.keys() == after_two.keys() and all(torch.equal(saved[k], after_two[k].cpu()) for k in saved)
    log = json.loads((tmp_path / "h.train.json").read_text())
    assert log["interrupted_after"] == 2 and len(log["epoch_loss"]) == 2 and log["epochs"] == 5

    calls.clear()  # before any epoch ended: nothing written, and said
    out.unlink()
    monkeypatch.setattr(FasterRCNNHead, "losses", lambda self, *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    assert main(args) == 130
    err = capsys.readouterr().err
    assert f"vpengine train detector: interrupted before the first epoch ended: nothing written to {out}" in err
    assert not out.exists()


def test_the_training_api_writes_the_last_finished_epoch_and_still_raises_the_interrupt(tmp_path, monkeypatch):
    # a script looping over trainings stops at a Ctrl-C, with what was trained written
    from vpengine.models.detection import FasterRCNNHead
    from vpengine.models.training import TrainingInterrupted, train_detector

    img_dir, ann, _ = make_dataset(tmp_path, n=2)
    cfg = write_config(tmp_path / "c.yaml")

    def on_epoch(epoch, *_):
        if epoch == 2:
            monkeypatch.setattr(FasterRCNNHead, "losses", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))

    with pytest.raises(TrainingInterrupted) as e:
        train_detector(cfg, img_dir, ann, tmp_path / "h.pth", epochs=4, batch_size=2, progress=False, threads=1,
                       on_epoch=on_epoch)  # fmt: skip
    assert isinstance(e.value, KeyboardInterrupt) and e.value.summary["interrupted_after"] == 2
    assert (tmp_path / "h.pth").is_file() and not list(tmp_path.glob(".*.part"))
    assert json.loads((tmp_path / "h.train.json").read_text())["interrupted_after"] == 2


def test_a_negative_weight_decay_is_refused_before_the_features(tmp_path, monkeypatch):
    from vpengine.models import training

    monkeypatch.setattr(training, "load_coco", lambda *a: pytest.fail("reached the dataset"))
    with pytest.raises(ValueError, match=r"weight_decay must be a number >= 0, got -1.0"):
        training.train_detector("tiny", tmp_path, tmp_path / "a.json", tmp_path / "h.pth", weight_decay=-1.0)
