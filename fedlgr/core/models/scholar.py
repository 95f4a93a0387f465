"""The scholar model (the paper's Fig. 2): a feature-extracting root and a task top.

* ``MobileNetRoot``: MobileNetV2 ``features`` + global average pool -> 1280-d (less for a
  width multiplier < 1); ImageNet weights, random init or a local state-dict file.
* ``MLPRoot``: the features modality - an MLP over the 27 descriptors + 2 mode flags (or
  the descriptors alone); with ``block="linear"`` one affine layer per hidden size, the
  LEAP-HRI'24 benchmark's model with ``Top(16, hidden=16)`` (docs/leap_hri24.md).
* ``Top``: BatchNorm1d -> Linear(., 32) -> BatchNorm1d(32) -> Linear(32, 8), linear
  activations, one output per action.
* ``Scholar``: root + top, with separate parameter groups (root and top learning rates);
  it is trained on the MSE averaged over the 8 actions (``fedlgr.core.client.training``).

Parameter names start with ``root.`` or ``top.``: that prefix is what FedRoot shares.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import TYPE_CHECKING

import lightning as L
import torch
from torch import nn

from fedlgr.core.data.columns import DESCRIPTOR_COLUMNS, FEATURE_COLUMNS, LABEL_COLUMNS
from fedlgr.errors import ConfigError, first_line

if TYPE_CHECKING:
    from fedlgr.core.settings import ExperimentConfig, ModelConfig


N_ACTIONS = len(LABEL_COLUMNS)
OFFLINE_ENV = "FEDLGR_OFFLINE"  # set to 1: never try to download weights


def _imagenet_state_dict() -> dict[str, torch.Tensor]:
    """torchvision's IMAGENET1K_V1 MobileNetV2 weights, from the torch hub cache or the web."""
    from torchvision.models import MobileNet_V2_Weights  # lazy: torchvision, for images only

    weights = MobileNet_V2_Weights.IMAGENET1K_V1
    cached = Path(torch.hub.get_dir()) / "checkpoints" / Path(weights.url).name
    how = (
        "Run without them with model.weights=none (random init), or put the file "
        f"{Path(weights.url).name} in {cached.parent} (or pass its path: model.weights=/path/to/it)"
    )
    if not cached.is_file() and os.environ.get(OFFLINE_ENV) == "1":
        raise ConfigError(f"model.weights=imagenet: {cached} is missing and {OFFLINE_ENV}=1. {how}")
    try:
        return weights.get_state_dict(progress=False, check_hash=True)
    except Exception as err:
        reason = first_line(err)
        raise ConfigError(
            f"model.weights=imagenet: cannot load the ImageNet weights ({reason}). {how}"
        ) from err


def file_state_dict(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise ConfigError(
            f"model.weights={path}: file not found (use imagenet, none or a file path)"
        )
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch.load raises KeyError, EOFError, RuntimeError, ...
        raise ConfigError(
            f"model.weights={path}: cannot read a state dict ({_unreadable(err)}); expected "
            "the tensors of a model saved with torch.save(model.state_dict(), file)"
        ) from err
    if isinstance(state, dict) and "state_dict" in state:
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ConfigError(
            f"model.weights={path}: expected a state dict, got {type(state).__name__}"
        )
    return state


def _unreadable(err: Exception) -> str:
    """Why torch.load failed, in a few words. torch's own text runs to several lines and
    recommends ``weights_only=False``, which would run whatever code the file holds."""
    text = str(err)
    found = re.search(r"Unsupported global: GLOBAL ([\w.]+)", text)
    if found:
        return f"it holds a pickled {found.group(1)}, not only tensors"
    if "PytorchStreamReader" in text or isinstance(err, EOFError):
        return "a truncated or damaged torch.save file"
    return "not a torch.save file"


class MobileNetRoot(L.LightningModule):
    """MobileNetV2 features + AdaptiveAvgPool2d(1) + flatten."""

    def __init__(self, weights: str = "none", width: float = 1.0):
        super().__init__()
        from torchvision.models import mobilenet_v2  # lazy: torchvision, for images only

        net = mobilenet_v2(weights=None, width_mult=width)
        if weights == "imagenet":
            net.load_state_dict(_imagenet_state_dict())
        elif weights != "none":
            self._load_file(net, Path(weights))
        self.features = net.features
        self.pool = nn.AdaptiveAvgPool2d(1)
        self.out_dim = net.last_channel

    @staticmethod
    def _load_file(net: nn.Module, path: Path) -> None:
        state = file_state_dict(path)
        # Accept a full torchvision MobileNetV2 state dict, or one saved from this root.
        state = {k.removeprefix("root."): v for k, v in state.items() if not k.startswith("top.")}
        features = {k: v for k, v in state.items() if k.startswith("features.")}
        try:
            missing, _ = net.load_state_dict(features, strict=False)
        except RuntimeError as err:  # shape mismatches: another width or architecture
            missing = [str(err).splitlines()[1].strip()]
        missing = [k for k in missing if "features." in k]
        if missing:
            raise ConfigError(
                f"model.weights={path}: not MobileNetV2 weights for this width "
                f"(model.width; e.g. {missing[0]})"
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.flatten(self.pool(self.features(x)), 1)

    def blocks(self) -> list[nn.Module]:
        """The root's blocks, input first: MobileNetV2's 19 ``features`` (the stem, 17
        inverted residual blocks, the last 1x1 convolution); the pool has no weights."""
        return list(self.features)

    def forward_to(self, x: torch.Tensor, block: int) -> torch.Tensor:
        """The activations entering block ``block`` (``forward_from`` goes on from them)."""
        return self.features[:block](x)

    def forward_from(self, z: torch.Tensor, block: int) -> torch.Tensor:
        return torch.flatten(self.pool(self.features[block:](z)), 1)


class MLPRoot(L.LightningModule):
    """Linear -> BatchNorm1d -> ReLU per hidden size (``block="linear"``: a Linear alone, so
    that the root is affine), over the descriptor features. ``columns``: the root reads only
    the first ``columns`` inputs (27: the descriptors, not the mode flags that follow them;
    None: all ``in_dim``)."""

    def __init__(
        self,
        in_dim: int = len(FEATURE_COLUMNS),
        hidden: tuple[int, ...] = (256, 256),
        block: str = "linear_bn_relu",
        columns: int | None = None,
    ):
        super().__init__()
        self.columns = columns
        in_dim = in_dim if columns is None else columns
        layers: list[nn.Module] = []
        for size in hidden:
            layers.append(nn.Linear(in_dim, size))
            if block == "linear_bn_relu":
                layers += [nn.BatchNorm1d(size), nn.ReLU(inplace=True)]
            in_dim = size
        self.per_block = len(layers) // len(hidden)
        self.net = nn.Sequential(*layers)
        self.out_dim = in_dim

    def _read(self, x: torch.Tensor) -> torch.Tensor:
        return x if self.columns is None else x[..., : self.columns]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(self._read(x))

    def blocks(self) -> list[nn.Module]:
        """The root's blocks, input first: one per hidden size (Linear -> BatchNorm1d ->
        ReLU, or the Linear alone)."""
        layers, k = list(self.net), self.per_block
        return [nn.Sequential(*layers[i : i + k]) for i in range(0, len(layers), k)]

    def forward_to(self, x: torch.Tensor, block: int) -> torch.Tensor:
        """The activations entering block ``block`` (``forward_from`` goes on from them)."""
        return self.net[: self.per_block * block](self._read(x))

    def forward_from(self, z: torch.Tensor, block: int) -> torch.Tensor:
        return self.net[self.per_block * block :](z)


class Top(L.LightningModule):
    """BatchNorm1d -> Linear(in, 32) -> BatchNorm1d(32) -> Linear(32, 8); linear activations."""

    def __init__(self, in_dim: int, hidden: int = 32, output_bias: float | None = 3.0):
        super().__init__()
        self.net = nn.Sequential(
            nn.BatchNorm1d(in_dim),
            nn.Linear(in_dim, hidden),
            nn.BatchNorm1d(hidden),
            nn.Linear(hidden, N_ACTIONS),
        )
        # Start at the middle of the Likert scale, so early rounds do not spend their
        # steps moving the output from 0 to the labels' range (architecture unchanged);
        # None: the Linear layer's own initialisation.
        if output_bias is not None:
            with torch.no_grad():
                self.net[-1].bias.fill_(output_bias)

    def forward(self, r: torch.Tensor) -> torch.Tensor:
        return self.net(r)


class Scholar(L.LightningModule):
    """Root + top; Adam with one parameter group each (the paper's lr_R and lr_T; its
    1e-3 and betas unless given: ``train.lr_root``, ``train.lr_top``, ``train.betas``).
    ``weight_decay``: Adam's L2 penalty on every parameter (``torch.optim.Adam``'s, added to
    the gradient before the moments, as the LEAP-HRI'24 code's Adam(lr=0.01,
    weight_decay=0.01); not AdamW's decoupled decay)."""

    def __init__(
        self,
        root: nn.Module,
        top: Top,
        lr_root: float = 1e-3,
        lr_top: float = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        weight_decay: float = 0.0,
    ):
        super().__init__()
        self.root, self.top = root, top
        self.lr_root, self.lr_top, self.betas = lr_root, lr_top, tuple(betas)
        self.weight_decay = weight_decay

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.top(self.root(x))

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(
            [
                {"params": self.root.parameters(), "lr": self.lr_root, "name": "root"},
                {"params": self.top.parameters(), "lr": self.lr_top, "name": "top"},
            ],
            betas=self.betas,
            weight_decay=self.weight_decay,
            fused=True,  # one kernel per step instead of a loop of foreach ops: ~4% per step on CPU
        )


def build_root(model: ModelConfig, kind: str) -> nn.Module:
    if kind == "mlp":
        columns = None if model.mode_flags else len(DESCRIPTOR_COLUMNS)
        return MLPRoot(hidden=tuple(model.mlp_hidden), block=model.mlp_block, columns=columns)
    return MobileNetRoot(model.weights, model.width)


def build_scholar(config: ExperimentConfig) -> Scholar:
    """The initial model of an experiment (call under a seed: the init is random)."""
    root = build_root(config.model, config.root_kind)
    top = Top(root.out_dim, config.model.top_hidden, config.model.output_bias)
    train = config.train
    scholar = Scholar(root, top, train.lr_root, train.lr_top, train.betas, train.weight_decay)
    if config.model.channels_last and config.root_kind == "mobilenet_v2":
        scholar = scholar.to(memory_format=torch.channels_last)
    return scholar
