"""DetectorModule(teacher=...): the teacher's detections as a second training target."""

import pytest
import torch

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.training.api import Detector
from lunarnav_ml.training.module import DetectorModule


@pytest.fixture(scope="module")
def teacher_path(tmp_path_factory):
    torch.manual_seed(0)
    model = DetectorModule("nano", img_size=64).model.eval()
    path = tmp_path_factory.mktemp("teacher") / "teacher.pt"
    Detector(model, 64, ["crater", "rock", "artifact"], "nano").save(path)
    return path, model.anchors.tolist()


def batch():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, 64, 64, generator=g)
    one = {"boxes": torch.tensor([[10.0, 12.0, 30.0, 34.0]]), "labels": torch.tensor([1]),
           "ignore": torch.tensor([False])}
    return x, [one, dict(one)]


def test_the_teacher_term_is_added_with_its_weight_and_trains(teacher_path):
    path, anchors = teacher_path
    torch.manual_seed(2)
    module = DetectorModule("nano", img_size=64, anchors=anchors, teacher=str(path),
                            teacher_weight=0.5)
    module.setup("fit")
    x, targets = batch()
    with_kd = module._losses(module.model, x, targets)
    kd = float(with_kd["kd"])
    assert kd > 0 and with_kd["loss"].requires_grad
    teacher, module._teacher = module._teacher, []
    plain = module._losses(module.model, x, targets)
    assert "kd" not in plain
    assert float(with_kd["loss"]) == pytest.approx(float(plain["loss"]) + 0.5 * kd, rel=1e-5)
    # the term has a gradient of its own, and the teacher none and no place in checkpoints
    module._teacher = teacher
    module.hparams.teacher_weight = 1.0
    module.model.zero_grad()
    module._losses(module.model, x, targets)["loss"].backward()
    with_grad = [p.grad.clone() for p in module.model.parameters()]
    module.model.zero_grad()
    module._teacher = []
    module._losses(module.model, x, targets)["loss"].backward()
    assert any(not torch.allclose(a, p.grad) for a, p in zip(with_grad, module.model.parameters()))
    assert all(p.grad is None for p in teacher[0].parameters())
    assert not any(k.startswith("_teacher") for k in module.state_dict())


def test_a_teacher_with_other_anchors_is_refused(teacher_path):
    path, anchors = teacher_path
    other = (torch.tensor(anchors) * 1.5).tolist()
    module = DetectorModule("nano", img_size=64, anchors=other, teacher=str(path))
    with pytest.raises(ConfigError, match="teacher .*anchors"):
        module.setup("fit")
    with pytest.raises(ConfigError, match="teacher_weight"):
        DetectorModule("nano", teacher_weight=-1.0)
