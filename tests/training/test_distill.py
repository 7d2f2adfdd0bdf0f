"""lunarnav distill-stem: the stride-2 stem trained to reproduce a small-relu teacher."""

import argparse
import copy

import numpy as np
import pytest
import torch

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.export.bench import random_detector, synthetic_frame
from lunarnav_ml.losses import detection_kd_loss
from lunarnav_ml.runtime.preprocess import prepare_batch
from lunarnav_ml.training import cli
from lunarnav_ml.training.api import Detector, load_detector
from lunarnav_ml.training.distill import distill_stem, student_from, torch_device


@pytest.fixture(scope="module")
def teacher():
    parts = random_detector("small-relu", img_size=64, seed=3, calib_batches=1)
    return Detector(parts.model, 64, list(parts.class_names), "small-relu")


@pytest.fixture(scope="module")
def images():
    frames = [synthetic_frame(64, seed=s) for s in range(24)]
    return prepare_batch(frames, (64, 64))[0]


def test_student_shares_all_but_the_stem(teacher):
    student = student_from(teacher, "small-relu-s2")
    own, theirs = student.state_dict(), teacher.model.state_dict()
    shared = [k for k in own if k in theirs]
    assert len(shared) > 300 and all(torch.equal(own[k], theirs[k]) for k in shared)
    assert {k.split(".")[1] for k in own if k not in theirs} == {"stem"}
    with pytest.raises(ConfigError, match="outside the stem"):
        student_from(teacher, "nano")


def test_distillation_learns_the_teacher_and_is_seeded(teacher, images):
    run = lambda f, o: distill_stem(teacher, images, feature_steps=f, output_steps=o, batch=4,
                                    held_out=8, seed=1, progress=False)
    _, untrained = run(0, 0)
    _, trained = run(30, 0)
    # (an untrained teacher on noise frames says nothing about the output phase's worth: that
    # is measured on the shipped model, BENCHMARKS.md issue 8)
    assert trained.feature_rel_err < 0.7 * untrained.feature_rel_err
    a, b = run(20, 5)[0], run(20, 5)[0]
    assert a.preset == "small-relu-s2" and a.img_size == 64
    for (k, v), w in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.equal(v, w), k
    assert all(p.requires_grad is False for p in teacher.model.parameters())


def test_detection_loss_is_zero_at_the_teacher_and_ignores_empty_cells():
    g = torch.Generator().manual_seed(0)
    # 2 anchors, 3 classes: 16 channels; one scale of 4 x 4 cells
    teacher = [torch.randn(1, 16, 4, 4, generator=g)]
    teacher[0][:, [4, 12]] = -12.0  # every anchor empty ...
    teacher[0][0, 4, 1, 2] = 6.0  # ... but anchor 0 at row 1, column 2
    at = detection_kd_loss(teacher, teacher, 2)
    assert abs(float(at)) < 1e-5  # a divergence: the teacher's entropy is taken off
    nudged = [t + 0.3 * torch.randn(t.shape, generator=g) for t in teacher]
    assert float(detection_kd_loss(nudged, teacher, 2)) > float(at)
    box = lambda row, col: [t.clone().index_put_((torch.tensor([0]), torch.tensor([0]),
                                                  torch.tensor([row]), torch.tensor([col])),
                                                 torch.tensor([3.0]), accumulate=True)
                            for t in teacher]
    full, empty = (float(detection_kd_loss(box(r, c), teacher, 2)) - float(at)
                   for r, c in ((1, 2), (3, 3)))
    assert full > 1.0 and empty < 1e-3 * full  # tx moved by 3: counts only where an object is
    student = [t.clone().requires_grad_(True) for t in teacher]
    detection_kd_loss(student, teacher, 2).backward()
    assert float(student[0].grad.abs().max()) < 1e-6  # the teacher is a minimum


def test_whole_phase_trains_every_weight_from_a_given_student(teacher, images):
    start = distill_stem(teacher, images, feature_steps=3, output_steps=0, batch=4, held_out=8,
                         seed=1, progress=False)[0]
    before = {k: v.clone() for k, v in start.model.state_dict().items()}
    run = lambda: distill_stem(teacher, images, feature_steps=0, output_steps=0, whole_steps=4,
                               batch=4, held_out=8, seed=2, whole_lr=1e-3, bf16=True,
                               student=Detector(copy.deepcopy(start.model), 64,
                                                start.class_names, start.preset),
                               progress=False)
    (a, report), (b, _) = run(), run()
    assert report.steps == (0, 0, 4)
    after = a.model.state_dict()
    moved = {k.split(".")[0] for k in after
             if after[k].is_floating_point() and not torch.equal(after[k], before[k])}
    assert moved == {"backbone", "neck", "head"}
    held = [k for k in after if k.endswith(("running_mean", "running_var"))]
    assert held and all(torch.equal(after[k], before[k]) for k in held)
    assert all(torch.equal(v, w) for v, w in zip(after.values(), b.model.state_dict().values()))
    with pytest.raises(ConfigError, match="student"):
        distill_stem(teacher, images, student=teacher, held_out=8, progress=False)


def test_bad_images_are_refused(teacher, images):
    bad = images.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(InputError, match="finite"):
        distill_stem(teacher, bad, progress=False)
    with pytest.raises(ConfigError, match="held_out"):
        distill_stem(teacher, images[:4], held_out=8, progress=False)
    with pytest.raises(ConfigError, match="'tpu'"):
        distill_stem(teacher, images, held_out=8, device="tpu", progress=False)
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA device"):
            distill_stem(teacher, images, held_out=8, device="cuda", progress=False)


def test_an_explicit_cpu_device_changes_nothing(teacher, images):
    run = lambda **kw: distill_stem(teacher, images, feature_steps=2, output_steps=0,
                                    whole_steps=2, batch=4, held_out=8, seed=2, progress=False,
                                    **kw)[0].model.state_dict()
    a, b = run(), run(device="cpu:0")
    assert all(torch.equal(v, w) for v, w in zip(a.values(), b.values()))
    assert all(v.device.type == "cpu" for v in b.values())
    assert torch_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_cli_writes_a_loadable_student(teacher, tmp_path):
    import cv2

    folder = tmp_path / "frames"
    folder.mkdir()
    for s in range(12):
        cv2.imwrite(str(folder / f"{s}.png"), synthetic_frame(64, seed=40 + s))
    path = tmp_path / "teacher.pt"
    teacher.save(path)
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    out = tmp_path / "student.pt"
    args = parser.parse_args(["distill-stem", "--teacher", str(path), "--images", str(folder),
                              "--out", str(out), "--feature-steps", "2", "--output-steps", "1",
                              "--batch", "2", "--quiet"])
    assert args.func(args) == 0
    student = load_detector(out)
    assert student.preset == "small-relu-s2" and student.img_size == 64
    again = tmp_path / "again.pt"
    args2 = parser.parse_args(["distill-stem", "--teacher", str(path), "--images", str(folder),
                               "--out", str(again), "--student", str(out), "--feature-steps",
                               "0", "--output-steps", "0", "--whole-steps", "2", "--batch", "2",
                               "--bf16", "--quiet"])
    assert args2.func(args2) == 0
    trained = load_detector(again).model.state_dict().values()
    assert not all(torch.equal(v, w) for v, w in zip(trained, student.model.state_dict().values()))
    args.out = tmp_path  # a folder: refused before any work
    with pytest.raises(InputError, match="existing folder"):
        args.func(args)
    missing = parser.parse_args(["distill-stem", "--teacher", str(path), "--images",
                                 str(tmp_path / "nowhere"), "--out", str(out)])
    with pytest.raises(InputError, match="nowhere"):
        missing.func(missing)
