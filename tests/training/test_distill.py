"""lunarnav distill-stem: the stride-2 stem trained to reproduce a small-relu teacher."""

import argparse

import numpy as np
import pytest
import torch

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.export.bench import random_detector, synthetic_frame
from lunarnav_ml.runtime.preprocess import prepare_batch
from lunarnav_ml.training import cli
from lunarnav_ml.training.api import Detector, load_detector
from lunarnav_ml.training.distill import distill_stem, student_from


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


def test_bad_images_are_refused(teacher, images):
    bad = images.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(InputError, match="finite"):
        distill_stem(teacher, bad, progress=False)
    with pytest.raises(ConfigError, match="held_out"):
        distill_stem(teacher, images[:4], held_out=8, progress=False)


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
    args.out = tmp_path  # a folder: refused before any work
    with pytest.raises(InputError, match="existing folder"):
        args.func(args)
    missing = parser.parse_args(["distill-stem", "--teacher", str(path), "--images",
                                 str(tmp_path / "nowhere"), "--out", str(out)])
    with pytest.raises(InputError, match="nowhere"):
        missing.func(missing)
