"""A Byzantine robot for the tests: on a SuperNode started with this folder on PYTHONPATH
(``FEDLGR_BYZANTINE=nan,scale,truncate,count,scores``), the robot service trains as any
robot does, then alters its n-th train reply as the n-th word says:

- ``nan``: every floating-point tensor NaN; ``scale``: every one x 1e6;
- ``truncate``: the packed tensor bytes cut short by 8 bytes;
- ``count``: a sample count of 10^12;
- ``scores``: the previous round's scores that the reply carries NaN;
- words joined by ``+`` do each (``count+scores``);
- ``honest``: nothing altered.

Python imports ``sitecustomize`` at start; this one only hooks the import of fedlgr's robot
module, so the SuperNode and its ClientApp processes stay as they are.
"""

from __future__ import annotations

import dataclasses
import importlib.abc
import importlib.util
import os
import sys

TARGET = "fedlgr.shell.deploy.flower.robot"
PLAN = [w for w in os.environ.get("FEDLGR_BYZANTINE", "").split(",") if w]


def alter(robot_module) -> None:
    wire = robot_module.wire
    honest = wire.encode_train_res
    replies = []

    def encode_train_res(res, evaluated=None):
        replies.append(1)
        how = PLAN[len(replies) - 1] if len(replies) <= len(PLAN) else "honest"
        print(f"byzantine: train reply {len(replies)}: {how}", flush=True)
        weights = dict(res.weights)
        for key, w in res.weights.items():
            if w.is_floating_point() and "nan" in how:
                weights[key] = w * float("nan")
            elif w.is_floating_point() and "scale" in how:
                weights[key] = w * 1e6
        n = 10**12 if "count" in how else res.n_samples
        res = dataclasses.replace(res, weights=weights, n_samples=n)
        if "scores" in how and evaluated is not None:
            nan = {k: float("nan") for k in evaluated.figures}
            evaluated = dataclasses.replace(evaluated, figures=nan)
        content = honest(res, evaluated)
        if "truncate" in how:
            array = content.array_records["shared"]["tensors"]
            array.data = array.data[:-8]
        return content

    wire.encode_train_res = encode_train_res


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
