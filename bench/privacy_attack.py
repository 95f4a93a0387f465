"""Membership inference on what fedlgr's server sees in one round (``bench/privacy.py``).

A robot (client 0) trains one round from the initial model with fedlgr's own
:class:`~fedlgr.core.client.side.ClientSide`; the server side is fedlgr's
:class:`~fedlgr.core.server.side.ServerSide`, with or without client-level DP
(``federated.dp.*``). A passive, honest-but-curious server then scores candidate scenes -
the robot's training scenes of the round (members) and as many test scenes that no robot
trained on (non-members, same distribution) - from one observation: the robot's own upload
(a plain server), the plain aggregate, or the DP release (clipped updates + Gaussian noise
over ``q N``: all a server under secure aggregation sees). Two published scores:

* **loss difference**: how much the observed tensors lower the candidate's loss against the
  model the round started from, ``l(theta_0, x) - l(theta_obs, x)``. Yeom et al.'s loss
  threshold (CSF 2018) made relative to the round's start, as in the passive attacker on
  updates of Nasr, Shokri & Houmansadr ("Comprehensive privacy analysis of deep learning",
  IEEE S&P 2019);
* **gradient alignment**: the cosine between the candidate's negative loss gradient at
  ``theta_0`` and the observed update ``theta_obs - theta_0`` (over the shared
  parameters): Li, Li & Ribeiro, "Effective passive membership inference attacks in
  federated learning against overparameterized models" (ICLR 2023).

With the whole model shared (scope ``full``) the attacker evaluates the observed model.
With the root only (scope ``root``) it never sees the robot's top: it puts the observed
root under the **initial top**, which the server holds (it built the round-1 model every
robot started from). In round 1 that top is exactly the one the robot's root was trained
under at its first step, so this favours the attacker; it has never seen any scene.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from fedlgr.core.client.side import ClientSide
from fedlgr.core.data.scenes import FederatedSplit, Scenes
from fedlgr.core.messages import RoundPlan, TrainRes, Weights
from fedlgr.core.privacy import epsilon
from fedlgr.core.scope import initial_scholar, shared_keys
from fedlgr.core.server.screen import update_norm
from fedlgr.core.server.side import ServerSide
from fedlgr.core.strategies import build_strategy
from fedlgr.shell.config import ExperimentConfig, load_config
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.splits import make_split

TARGET = 0  # the robot whose membership is attacked
ATTACKS = ("loss_diff", "grad_cos")


@dataclass
class Round:
    """One round of fedlgr's federation: the config, the data, the model the round started
    from, every robot's upload, and the candidates (member first, then non-member rows)."""

    config: ExperimentConfig
    scenes: Scenes
    split: FederatedSplit
    initial: nn.Module
    uploads: list[TrainRes]
    candidates: torch.Tensor
    members: torch.Tensor  # 1 for a member, 0 for a non-member


def train_round(overrides: list[str], seed: int, base: Path | None = None) -> Round:
    """fedlgr's round 1 for ``base`` (a config file; None: the defaults), ``overrides`` and
    ``seed``: the robots the strategy chooses train and upload."""
    config = load_config(base, [*overrides, f"seed={seed}"])
    scenes = load_scenes(config.data)
    split = make_split(scenes.table, config.data)
    server = ServerSide(config)
    robots = ClientSide(
        config, scenes, split, list(range(config.data.clients)), torch.device("cpu")
    )
    plan = RoundPlan(1, 0, True, True)
    ins = {c: server.train_ins(plan, c) for c in server.chosen(plan)}
    uploads = robots.train(ins)
    uploads = [
        TrainRes(r.client, {k: v.detach().clone() for k, v in r.weights.items()}, r.n_samples)
        for r in uploads
    ]
    members = split.clients[TARGET].train
    rng = np.random.default_rng(seed)
    outsiders = rng.choice(split.test, size=min(len(members), len(split.test)), replace=False)
    rows = torch.as_tensor(np.concatenate([members, outsiders]))
    labels = torch.cat([torch.ones(len(members)), torch.zeros(len(outsiders))])
    return Round(config, scenes, split, initial_scholar(config), uploads, rows, labels)


def clip_norm(round_: Round) -> float:
    """The median norm of the round's updates (what adaptive clipping aims at with its
    default quantile 0.5): half the robots' updates are clipped."""
    shared = ServerSide(round_.config).global_weights
    return float(np.median([update_norm(r, shared) for r in round_.uploads]))


def release(round_: Round, clip: float = 0.0, noise: float = 0.0) -> Weights:
    """What fedlgr's server holds after aggregating the round's uploads: the plain
    sample-weighted mean (``clip`` 0), or the DP release (clip, noise multiplier)."""
    config = round_.config
    dp = dataclasses.replace(config.federated.dp, clip=clip, noise_multiplier=noise)
    config = dataclasses.replace(config, federated=dataclasses.replace(config.federated, dp=dp))
    server = ServerSide(config)
    # what the robots upload under that config: under DP BatchNorm's running statistics
    # stay on them (fedlgr.core.scope), so their uploads hold the server's keys only
    uploads = [
        dataclasses.replace(r, weights={k: r.weights[k] for k in server.keys})
        for r in round_.uploads
    ]
    server.aggregate(uploads)
    if server.refused:  # a refused upload would leave a release of noise alone
        raise RuntimeError(f"the server refused uploads: {server.refused}")
    return server.global_weights


def one_round_epsilon(config: ExperimentConfig, noise: float) -> float:
    """The accountant's epsilon of one release at ``noise`` (fedlgr.core.privacy.epsilon)."""
    dp = config.federated.dp
    return epsilon(noise, config.federated.fraction, 1, dp.delta)


def gradients(round_: Round) -> tuple[list[str], torch.Tensor]:
    """The shared parameters' names and each candidate's loss gradient at the round's start
    (candidates x parameters, float64; eval mode, as the attacker scores one scene)."""
    model = copy.deepcopy(round_.initial).double().eval()
    keys = shared_keys(
        model, round_.config.federated.scope, build_strategy(round_.config.federated)
    )
    params = dict(model.named_parameters())
    names = [n for n in params if n in keys]
    x = round_.scenes.inputs[round_.candidates].double()
    y = round_.scenes.targets[round_.candidates].double()
    rows = []
    for i in range(len(x)):  # one scene at a time: per-example gradients
        loss = nn.functional.mse_loss(model(x[i : i + 1]), y[i : i + 1])
        grads = torch.autograd.grad(loss, [params[n] for n in names])
        rows.append(torch.cat([g.flatten() for g in grads]))
    return names, torch.stack(rows)


def scores(round_: Round, observed: Weights, grads: tuple[list[str], torch.Tensor]) -> dict:
    """Both attacks' membership scores of the round's candidates from ``observed`` (the
    shared tensors the server saw; the rest of the model is the initial one), in float64
    (a release that noise has wrecked still ranks the candidates)."""
    before = copy.deepcopy(round_.initial).double().eval()
    after = copy.deepcopy(before)
    after.load_state_dict(observed, strict=False)
    x = round_.scenes.inputs[round_.candidates].double()
    y = round_.scenes.targets[round_.candidates].double()
    with torch.no_grad():
        loss_diff = _losses(before, x, y) - _losses(after, x, y)
    names, per_scene = grads
    start = before.state_dict()
    update = torch.cat([(observed[n].double() - start[n]).flatten() for n in names])
    grad_cos = nn.functional.cosine_similarity(-per_scene, update[None, :], dim=1)
    return {"loss_diff": loss_diff, "grad_cos": grad_cos}


def _losses(model: nn.Module, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-scene MSE over the 8 actions (``model`` in eval mode)."""
    return (model(x) - y).pow(2).mean(dim=1)


def auc(score: torch.Tensor, members: torch.Tensor) -> float:
    """The attack's ROC AUC, the Mann-Whitney statistic: the chance that a member scores
    above a non-member, ties counting half (0.5: it cannot tell them apart). Computed on
    the raw scores: torchmetrics' AUROC squashes scores outside [0, 1] with a sigmoid,
    which ties every score of a wrecked model."""
    inside, outside = score[members == 1], score[members == 0]
    above = (inside[:, None] > outside[None, :]).double().mean()
    tied = (inside[:, None] == outside[None, :]).double().mean()
    return float(above + tied / 2)


def observations(round_: Round, noises: list[float]) -> dict[str, tuple[Weights, float | None]]:
    """What the server may see, by name, with each one's one-round epsilon (None: no DP):
    the robot's upload, the plain aggregate, the DP release at each noise multiplier."""
    upload = next(r for r in round_.uploads if r.client == TARGET).weights
    seen = {"upload": (upload, None), "aggregate": (release(round_), None)}
    clip = clip_norm(round_)
    for z in noises:
        seen[f"DP z={z:g}"] = (release(round_, clip, z), one_round_epsilon(round_.config, z))
    return seen
