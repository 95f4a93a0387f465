"""A Byzantine robot for the tests: on a SuperNode started with this folder on PYTHONPATH
(``FEDLGR_BYZANTINE=nan,scale,truncate,count,scores``), the robot service trains as any
robot does, then alters its n-th train reply as the n-th word says:

- ``nan``: every floating-point tensor NaN; ``scale``: every one x 1e6;
- ``truncate``: the packed tensor bytes cut short by 8 bytes;
- ``count``: a sample count of 10^12;
- ``scores``: the previous round's scores that the reply carries NaN;
- ``liar`` (issue 50): those scores too good to be true - every error 0.01, every
  correlation 0.99 - yet each in its range;
- (issue 50) ``payload8``: every payload tensor x 8; ``replay``: the upload this robot sent
  in its previous train reply (as it was sent), sent again;
- words joined by ``+`` do each (``count+scores``);
- ``honest``: nothing altered.
- (fault sweep 37) ``figkey``: a training figure that is not the run's; ``strfig``: a
  string where a figure's number goes; ``boolcount``: a sample count of True;
  ``nofigures``: the figures record left out; ``client``: the upload claims client 0;
  ``extra``: an extra tensor; ``half``: the first float tensor as float16; ``zeros``:
  every tensor zero; ``payload``: every payload tensor NaN (or, where the strategy sends
  none, a NaN payload record of its own); ``bigendian``: the tensors' index says >f4.
- (issue 50) ``secscale``, in a SecAgg+ round (``deploy.secagg``, whose train reply is the
  robot's vector, :func:`fedlgr.shell.deploy.flower.masked.robot_vector`): its update and
  payload x 1000 before masking, unclipped (its weight, and DP's bit, as they are).

Python imports ``sitecustomize`` at start; this one only hooks the import of fedlgr's robot
module, so the SuperNode and its ClientApp processes stay as they are.
"""

from __future__ import annotations

import dataclasses
import importlib.abc
import importlib.util
import math
import os
import sys

TARGET = "fedlgr.shell.deploy.flower.robot"
PLAN = [w for w in os.environ.get("FEDLGR_BYZANTINE", "").split(",") if w]


def alter(robot_module) -> None:
    wire, masked = robot_module.wire, robot_module.masked
    honest, honest_vector = wire.encode_train_res, masked.robot_vector
    replies = []  # one per train reply
    sent = []  # each upload as it was sent (replay)

    def next_word() -> str:
        replies.append(1)
        how = PLAN[len(replies) - 1] if len(replies) <= len(PLAN) else "honest"
        print(f"byzantine: train reply {len(replies)}: {how}", flush=True)
        return how

    def robot_vector(res, start, settings):
        how = next_word()
        if "secscale" not in how:
            return honest_vector(res, start, settings)
        import numpy as np  # here: every process with this PYTHONPATH imports this module

        dp = float(settings["clip"]) > 0
        unclipped = {**settings, "clip": math.inf if dp else 0.0, "norm_bound": math.inf}
        vector, _, size = honest_vector(res, start, unclipped)
        vector[: -2 if dp else -1] *= 1000  # not the weight (nor DP's bit): the last values
        outside = int(np.count_nonzero(np.abs(vector) > float(settings["clipping_range"])))
        return vector, outside, size

    def encode_train_res(res, evaluated=None):
        how = next_word()
        if "replay" in how and sent:
            res = sent[-1]
        weights = dict(res.weights)
        for key, w in res.weights.items():
            if w.is_floating_point() and "nan" in how:
                weights[key] = w * float("nan")
            elif w.is_floating_point() and "scale" in how:
                weights[key] = w * 1e6
        if "zeros" in how:
            weights = {k: w * 0 for k, w in weights.items()}
        if "half" in how:
            key = next(k for k, w in weights.items() if w.is_floating_point())
            weights[key] = weights[key].half()
        if "extra" in how:
            import torch

            weights["evil.tensor"] = torch.zeros(3)
        n = 10**12 if "count" in how else res.n_samples
        n = True if "boolcount" in how else n
        figures = dict(res.figures)
        if "figkey" in how:
            figures["evil/figure"] = 1.0
        if "strfig" in how:
            figures[next(iter(figures))] = "abc"
        payload = dict(res.payload)
        if "payload" in how.split("+"):  # not payload8
            import torch

            payload = {k: v * float("nan") for k, v in payload.items()} or {
                "scaffold/evil": torch.full((3,), float("nan"))
            }
        if "payload8" in how:
            payload = {k: v * 8 for k, v in payload.items()}
        client = 0 if "client" in how else res.client
        res = dataclasses.replace(
            res, weights=weights, n_samples=n, figures=figures, payload=payload, client=client
        )
        # as sent: the model's own tensors train on after the reply
        sent.append(
            dataclasses.replace(
                res,
                weights={k: w.clone() for k, w in res.weights.items()},
                payload={k: v.clone() for k, v in res.payload.items()},
            )
        )
        if "scores" in how and evaluated is not None:
            nan = {k: float("nan") for k in evaluated.figures}
            evaluated = dataclasses.replace(evaluated, figures=nan)
        if "liar" in how and evaluated is not None:
            good = {
                k: (0.99 if k.split("/")[-1] in ("pcc", "ccc") else 0.01)
                if k.startswith(("test/", "task/"))
                else v
                for k, v in evaluated.figures.items()
            }
            evaluated = dataclasses.replace(evaluated, figures=good)
        content = honest(res, evaluated)
        if "truncate" in how:
            array = content.array_records["shared"]["tensors"]
            array.data = array.data[:-8]
        if "nofigures" in how:
            del content["figures"]
        if "bigendian" in how:
            from flwr.app import ConfigRecord

            index = content.config_records["shared.index"]
            content["shared.index"] = ConfigRecord(
                {**dict(index), "dtypes": [">f4" for _ in index["dtypes"]]}
            )
        return content

    wire.encode_train_res = encode_train_res
    masked.robot_vector = robot_vector


class _Hook(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name != TARGET:
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            alter(module)

        spec.loader.exec_module = exec_module
        return spec


if PLAN:
    sys.meta_path.insert(0, _Hook())
