import pytest
import torch

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.models import PRESETS, build_model, count_parameters, default_anchors


@pytest.mark.parametrize("size", [(64, 64), (96, 128)])
def test_nano_output_shapes_every_scale(size):
    model = build_model("nano", num_classes=3).eval()
    h, w = size
    with torch.no_grad():
        out = model(torch.rand(2, 3, h, w))
    assert model.strides == (8, 16, 32)
    assert [tuple(o.shape) for o in out] == [(2, 3 * 8, h // s, w // s) for s in (8, 16, 32)]


def test_tiny_has_two_heads():
    model = build_model("tiny", num_classes=3).eval()
    with torch.no_grad():
        out = model(torch.rand(1, 3, 64, 64))
    assert model.strides == (16, 32)
    assert [tuple(o.shape) for o in out] == [(1, 24, 4, 4), (1, 24, 2, 2)]


def test_presets_grow_in_size():
    sizes = [count_parameters(build_model(p)) for p in ("nano", "small", "medium")]
    assert sizes == sorted(sizes) and sizes[0] < 3e6
    assert set(PRESETS) >= {"nano", "tiny", "small", "medium", "yolov4"}


@pytest.mark.slow
def test_full_yolov4_matches_reference_parameter_count():
    # reference darknet YOLOv4 (80 classes, 608 px): 64.36 M parameters
    assert count_parameters(build_model("yolov4", 80)) == pytest.approx(64.36e6, rel=0.01)


def test_bad_arguments_raise():
    with pytest.raises(ConfigError, match=r"preset: unknown model preset 'huge' \(known: nano, "):
        build_model("huge")
    with pytest.raises(ConfigError, match="unknown model preset 'huge'"):
        default_anchors("huge")
    with pytest.raises(ConfigError, match="num_classes: must be an integer >= 1, got 0"):
        build_model("nano", num_classes=0)
    with pytest.raises(ValueError, match="anchors"):
        build_model("nano", anchors=[[10, 10]])
    with pytest.raises(ValueError, match="multiples of 32"):
        build_model("nano")(torch.rand(1, 3, 70, 64))
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        build_model("nano")(torch.rand(1, 1, 64, 64))


def test_set_anchors_checks_shape():
    model = build_model("nano")
    new = torch.arange(18, dtype=torch.float32).view(3, 3, 2) + 1
    model.set_anchors(new)
    assert torch.equal(model.anchors, new)
    with pytest.raises(ValueError, match="shape"):
        model.set_anchors(torch.ones(2, 3, 2))


def test_small_relu_is_small_with_relu_throughout():
    small, relu = build_model("small"), build_model("small-relu")
    assert count_parameters(relu) == count_parameters(small)
    relu.load_state_dict(small.state_dict())  # the leaky small's weights start its fine-tuning
    acts = {type(m) for m in relu.modules()
            if isinstance(m, (torch.nn.ReLU, torch.nn.LeakyReLU, torch.nn.Mish))}
    assert acts == {torch.nn.ReLU}
