"""The GPU checks in one call (issue 25). Run: ``uv run python bench/gpu.py``.

On a machine with a CUDA GPU, in this order, each part printing its figures:

1. the CUDA-only tests (``pytest -m gpu``: tests/test_gpu.py);
2. clients trained one after another (``runtime.concurrency=sequential``), side by side in
   threads with a CUDA stream each (``threads``) and stacked into one model (``batched``),
   for 2 and 10 clients, one round, measured side by side in each repeat (the order
   rotates): images/s and the ratios to sequential, with each client's GPU seconds
   (``cost/gpu_s``, its span on its stream) beside NVML's device-wide utilisation;
3. FedAvg vs FedRootAvg, 2 rounds: test RMSE, CPU s, GPU s, NVML %, peak memory and
   bytes up per client per round;
4. ``train.precision`` 32-true vs 16-mixed vs bf16-mixed: images/s, that every loss is
   finite and the test RMSE is within noise of fp32;
5. peak GPU memory per client (from part 2 and 3).

Without CUDA it says so in one line and runs what it can on the CPU (part 2 for 2
clients, small) and exits 0. ``--json FILE`` writes every figure too. On a device with no
network, run it with an environment that already holds the locked packages.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

from train import settings as train_settings  # bench/train.py, beside this script

ROOT = Path(__file__).resolve().parent.parent
MODES = ("sequential", "threads", "batched")


def settings(tmp: str, args, clients: int, *extra: str) -> list[str]:
    """bench/train.py's one-round settings, without progress bars."""
    return train_settings(tmp, args, clients, "runtime.progress=false", *extra)


def environment() -> dict:
    import torch

    from fedlgr.core.meters.costs import nvml_available

    cuda = torch.cuda.is_available()
    return {
        "date": str(date.today()),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda if cuda else None,
        "device": torch.cuda.get_device_name(0) if cuda else platform.processor() or "cpu",
        "nvml": nvml_available() if cuda else False,
    }


def cuda_tests() -> dict:
    """``pytest -m gpu`` in a child process; its summary line."""
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-m", "gpu", "-q", "-o", "addopts=-ra", "tests"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    lines = [line for line in done.stdout.splitlines() if line.strip()]
    print("\n".join(lines[-15:]))
    return {"returncode": done.returncode, "summary": lines[-1] if lines else ""}


def one_round(overrides: list[str], device) -> tuple[float, list]:
    """Images/s of one training round of a fresh ClientSide, and its clients' usage."""
    from fedlgr.core.client.side import ClientSide
    from fedlgr.core.messages import RoundPlan, TrainIns
    from fedlgr.shell.config import load_config
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.data.splits import make_split

    config = load_config(None, overrides)
    scenes = load_scenes(config.data)
    split = make_split(scenes.table, config.data)
    side = ClientSide(config, scenes, split, list(range(config.data.clients)), device)
    start = time.perf_counter()
    trained = side.train(TrainIns(RoundPlan(1, 0, True, True)))
    seconds = time.perf_counter() - start
    samples = sum(t.figures["train/samples"] for t in trained)
    return samples / seconds, [t.figures for t in trained]


def concurrency(tmp: str, args, device, clients_list) -> dict:
    """Part 2: sequential vs threads vs batched, side by side in each repeat."""
    import torch

    out: dict = {}
    for clients in clients_list:
        rates: dict[str, list[float]] = {m: [] for m in MODES}
        usages: dict[str, list] = {}
        threads = torch.get_num_threads()
        accelerator = "gpu" if device.type == "cuda" else "cpu"
        for repeat in range(-1, args.repeats):  # -1: one untimed warm-up of each mode
            order = MODES[repeat % 3 :] + MODES[: repeat % 3]
            for mode in order:
                extra = [
                    f"runtime.concurrency={mode}",
                    f"runtime.threads={threads}",
                    f"runtime.accelerator={accelerator}",
                ]
                rate, usage = one_round(settings(tmp, args, clients, *extra), device)
                if repeat < 0:
                    continue
                rates[mode].append(rate)
                usages[mode] = usage
        fig = {f"{m}_img_s": statistics.median(v) for m, v in rates.items()}
        for mode in ("threads", "batched"):
            fig[f"{mode}_vs_sequential"] = statistics.median(
                a / b for a, b in zip(rates[mode], rates["sequential"], strict=True)
            )
        for mode, usage in usages.items():
            spans = [u["cost/gpu_s"] for u in usage if "cost/gpu_s" in u]
            if spans:
                fig[f"{mode}_gpu_s_per_client"] = statistics.mean(spans)
            util = [u["cost/gpu_util"] for u in usage if "cost/gpu_util" in u]
            if util:
                fig[f"{mode}_nvml_util_pct"] = statistics.mean(util)
            mem = [u["cost/gpu_mem_mb"] for u in usage if "cost/gpu_mem_mb" in u]
            if mem:
                fig[f"{mode}_peak_mem_mb_per_client"] = max(mem)
        print(f"  {clients} clients, one round of {args.epochs} epochs at {args.size} px:")
        for name, value in fig.items():
            print(f"    {name:<32}{value:10.2f}")
        out[f"{clients}_clients"] = fig
    return out


def methods(tmp: str, args) -> dict:
    """Part 3: FedAvg vs FedRootAvg on the GPU, 2 rounds."""
    from fedlgr.shell.config import load_config
    from fedlgr.shell.run.experiment import run_experiment

    out = {}
    for method in ("FedAvg", "FedRootAvg"):
        overrides = settings(tmp, args, 2, f"method={method}", "runtime.accelerator=gpu")
        result = run_experiment(load_config(None, [*overrides, "federated.rounds=2"]))
        costs = result.cost_means()
        fig = {"test_rmse": result.final.mean("test_rmse") or math.nan}
        for key in ("cpu_s", "gpu_s", "gpu_util", "gpu_mem_mb", "bytes_up"):
            fig[key] = costs.get(f"mean/cost/{key}", math.nan)
        out[method] = fig
        print(f"  {method:<11}" + "  ".join(f"{k} {v:.3g}" for k, v in fig.items()))
    return out


def precisions(tmp: str, args) -> dict:
    """Part 4: fp32 vs 16-mixed vs bf16-mixed on the GPU, 2 rounds each."""
    import torch

    from fedlgr.shell.config import load_config
    from fedlgr.shell.run.experiment import run_experiment

    out = {}
    for precision in ("32-true", "16-mixed", "bf16-mixed"):
        if precision == "bf16-mixed" and not torch.cuda.is_bf16_supported():
            print("  bf16-mixed: not supported by this GPU")
            continue
        overrides = settings(tmp, args, 2, f"train.precision={precision}")
        overrides += ["runtime.accelerator=gpu", "federated.rounds=2"]
        start = time.perf_counter()
        result = run_experiment(load_config(None, overrides))
        seconds = time.perf_counter() - start
        rows = result.rows()
        samples = sum(r["train_samples"] for r in rows)
        fig = {
            "img_s": samples / seconds,
            "losses_finite": float(all(math.isfinite(r["train_loss"]) for r in rows)),
            "test_rmse": result.final.mean("test_rmse") or math.nan,
        }
        out[precision] = fig
        print(f"  {precision:<11}" + "  ".join(f"{k} {v:.4g}" for k, v in fig.items()))
    if "32-true" in out:
        base = out["32-true"]["test_rmse"]
        for fig in out.values():
            fig["rmse_vs_fp32"] = fig["test_rmse"] - base
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=400, help="synthetic scenes (3/4 train)")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--epochs", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path, help="write every figure to this file")
    args = parser.parse_args()

    import torch

    from fedlgr.shell.data.synth import synthesize
    from fedlgr.shell.machine import tune_allocator

    tune_allocator()
    figures: dict = {"environment": environment()}
    print("environment: " + ", ".join(f"{k} {v}" for k, v in figures["environment"].items()))
    cuda = torch.cuda.is_available()
    with tempfile.TemporaryDirectory(prefix="fedlgr-gpu-") as tmp:
        if not cuda:
            print("no CUDA: torch.cuda.is_available() is False; the GPU parts are skipped")
            args.scenes, args.size, args.repeats = min(args.scenes, 200), 64, 1
            synthesize(Path(tmp) / "synth", args.scenes, seed=0, size=args.size)
            print("CPU part: sequential vs threads vs batched")
            figures["cpu_concurrency"] = concurrency(tmp, args, torch.device("cpu"), [2])
        else:
            synthesize(Path(tmp) / "synth", args.scenes, seed=0, size=args.size)
            print("1. CUDA tests (pytest -m gpu)")
            figures["cuda_tests"] = cuda_tests()
            device = torch.device("cuda", 0)
            print("2. sequential vs threads vs batched on the GPU")
            figures["gpu_concurrency"] = concurrency(tmp, args, device, [2, 10])
            print("3. FedAvg vs FedRootAvg on the GPU (per client per round)")
            figures["methods"] = methods(tmp, args)
            print("4. precision")
            figures["precision"] = precisions(tmp, args)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
