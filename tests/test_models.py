"""The scholar: root and top shapes, parameter groups, weights sources and their errors."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from fedlgr.core.models.scholar import (
    OFFLINE_ENV,
    MLPRoot,
    MobileNetRoot,
    Scholar,
    Top,
    build_scholar,
)
from fedlgr.errors import ConfigError
from fedlgr.shell.config import load_config


def test_mobilenet_root_pools_to_1280():
    root = MobileNetRoot(width=0.1).eval()
    out = root(torch.randn(2, 3, 32, 32))
    assert out.shape == (2, 1280) and root.out_dim == 1280


def test_top_is_bn_32_bn_8_with_linear_activations():
    top = Top(1280)
    kinds = [type(m) for m in top.net]
    assert kinds == [nn.BatchNorm1d, nn.Linear, nn.BatchNorm1d, nn.Linear]
    assert (top.net[1].in_features, top.net[1].out_features, top.net[3].out_features) == (
        1280,
        32,
        8,
    )
    assert torch.all(top.net[3].bias == 3.0)  # starts mid-Likert


def test_mlp_root_reads_29_features():
    root = MLPRoot(hidden=(16, 8)).eval()
    assert root(torch.randn(3, 29)).shape == (3, 8) and root.out_dim == 8


def test_a_linear_mlp_root_is_one_affine_layer_over_the_descriptors_alone():
    """The LEAP-HRI'24 FCL model's first layer: Linear(27, 16), the mode flags unread."""
    root = MLPRoot(hidden=(16,), block="linear", columns=27).eval()
    assert [type(m) for m in root.net] == [nn.Linear] and root.net[0].in_features == 27
    x = torch.randn(5, 29)
    flags_changed = x.clone()
    flags_changed[:, 27:] += 1
    assert torch.equal(root(x), root(flags_changed))
    assert torch.allclose(root(2 * x) - root(x), root(x) - root(0 * x), atol=1e-6)  # affine
    assert len(root.blocks()) == 1 and torch.equal(root.forward_to(x, 0), x[:, :27])
    two = MLPRoot(hidden=(16, 8), block="linear")
    assert len(two.blocks()) == 2
    assert torch.equal(two.forward_from(two.forward_to(x, 1), 1), two(x))


def test_top_keeps_the_linear_layer_s_own_bias_without_an_output_bias():
    torch.manual_seed(0)
    bias = Top(16, hidden=16, output_bias=None).net[3].bias
    assert bias.abs().max() <= 1 / 4 and len(set(bias.tolist())) == 8  # U(-1/sqrt(16), ..)


def test_weight_decay_is_adam_s_l2_term_and_off_by_default():
    """train.weight_decay: torch.optim.Adam's weight_decay (added to the gradient, as the
    LEAP-HRI'24 code's Adam(lr=0.01, weight_decay=0.01)), not AdamW's; 0 by default, which
    is the optimiser every run had before it."""
    for overrides, decay in (([], 0.0), (["train.weight_decay=0.01"], 0.01)):
        config = load_config(None, ["model.width=0.1", *overrides])
        optimizer = build_scholar(config).configure_optimizers()
        assert type(optimizer) is torch.optim.Adam
        for group in optimizer.param_groups:
            assert group["weight_decay"] == decay and not group["decoupled_weight_decay"]
    # one step by hand: Adam's first step is lr x sign(g + wd x theta), so the decay flips
    # a parameter whose gradient is smaller than wd x theta
    theta = nn.Parameter(torch.tensor([2.0]))
    step = torch.optim.Adam([theta], lr=0.1, weight_decay=0.01)
    theta.grad = torch.tensor([-0.01])  # g + wd x theta = -0.01 + 0.02 > 0
    step.step()
    assert theta.item() == pytest.approx(1.9, abs=1e-6)


def test_separate_parameter_groups_and_learning_rates():
    config = load_config(None, ["train.lr_root=1e-5", "train.lr_top=2e-3", "model.width=0.1"])
    model = build_scholar(config)
    groups = model.configure_optimizers().param_groups
    assert [(g["name"], g["lr"]) for g in groups] == [("root", 1e-5), ("top", 2e-3)]
    assert sum(p.numel() for p in groups[0]["params"]) == sum(
        p.numel() for p in model.root.parameters()
    )
    assert all(name.startswith(("root.", "top.")) for name in model.state_dict())


def test_imagenet_weights_unavailable_fail_with_a_clear_message(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty hub cache
    monkeypatch.setenv(OFFLINE_ENV, "1")  # and no download attempt
    with pytest.raises(ConfigError) as err:
        MobileNetRoot(weights="imagenet")
    message = str(err.value)
    assert message.startswith("model.weights=imagenet: ")
    assert "model.weights=none" in message and "mobilenet_v2-b0353104.pth" in message


def test_weights_from_a_local_file(tmp_path):
    torch.manual_seed(1)
    source = Scholar(MobileNetRoot(width=0.1), Top(1280))
    path = tmp_path / "root.pt"
    torch.save(source.state_dict(), path)
    loaded = MobileNetRoot(weights=str(path), width=0.1)
    assert torch.equal(loaded.features[0][0].weight, source.root.features[0][0].weight)
    # A full torchvision MobileNetV2 state dict works too.
    from torchvision.models import mobilenet_v2

    net = mobilenet_v2(width_mult=0.1)
    torch.save(net.state_dict(), tmp_path / "tv.pt")
    assert torch.equal(
        MobileNetRoot(str(tmp_path / "tv.pt"), 0.1).features[1].conv[0][0].weight,
        net.features[1].conv[0][0].weight,
    )


def test_bad_weight_files_name_the_setting(tmp_path):
    with pytest.raises(ConfigError, match=r"model\.weights=.*nope\.pt: file not found"):
        MobileNetRoot(weights=str(tmp_path / "nope.pt"))
    (tmp_path / "junk.pt").write_bytes(b"junk")
    with pytest.raises(ConfigError, match=r"junk\.pt: cannot read a state dict"):
        MobileNetRoot(weights=str(tmp_path / "junk.pt"))
    torch.save(MobileNetRoot(width=0.1).state_dict(), tmp_path / "narrow.pt")
    with pytest.raises(ConfigError, match="not MobileNetV2 weights for this width"):
        MobileNetRoot(weights=str(tmp_path / "narrow.pt"), width=1.0)


def _truncated_checkpoint(path):
    torch.save({"features.0.0.weight": torch.ones(4, 3, 3, 3)}, path)
    path.write_bytes(path.read_bytes()[:200])


WEIGHT_FILES = {
    "notes.txt": (lambda p: p.write_text("weights: none\n"), "not a torch.save file"),
    "hello.txt": (lambda p: p.write_text("hello\n"), "not a torch.save file"),
    "empty.pt": (lambda p: p.write_bytes(b""), "a truncated or damaged torch.save file"),
    "cut.pt": (_truncated_checkpoint, "a truncated or damaged torch.save file"),
    "module.pt": (
        lambda p: torch.save(torch.nn.Linear(2, 2), p),
        "it holds a pickled torch.nn.modules.linear.Linear, not only tensors",
    ),
}


@pytest.mark.parametrize("name", WEIGHT_FILES)
def test_a_weights_file_that_is_no_checkpoint_is_one_line(tmp_path, name):
    write, reason = WEIGHT_FILES[name]
    path = tmp_path / name
    write(path)
    with pytest.raises(ConfigError) as err:
        MobileNetRoot(weights=str(path), width=0.1)
    assert str(err.value) == (
        f"model.weights={path}: cannot read a state dict ({reason}); expected the tensors "
        "of a model saved with torch.save(model.state_dict(), file)"
    )
    assert "weights_only" not in str(err.value)
