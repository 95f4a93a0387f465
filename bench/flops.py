"""GFLOP per CPU-second of a training round, next to the core's peak (issue 48).
Run: ``uv run python bench/flops.py``.

One real training round of one client of the demo (``conf/experiment/demo.yaml``:
half-width random-init MobileNetV2, 128 px, batch 16, 2 augmented copies, one local epoch)
on synthetic scenes, with one torch thread. Printed: the round's counted GFLOP
(``cost/gflops``, :mod:`fedlgr.core.meters.flops`), the process's CPU seconds over the
round, their ratio, and the core's peak GFLOP/s from its clock and vector width (FMA lanes
x FMA units x 2 x GHz); the ratio must be below the peak (exit status 1 if not). Also
printed: each image's forward and training count, and the training count torch's own
FlopCounterMode gives (it over-counts grouped convolutions' backward pass), with the rate
that count would imply. The operation count is done before the round is timed (it is
cached), so the round's CPU seconds are its training's: gathering and augmenting the
batches, forward, backward, Adam.
"""

from __future__ import annotations

import argparse
import copy
import platform
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import date
from pathlib import Path

from figures import report  # bench/figures.py

REPO = Path(__file__).resolve().parent.parent
FMA_UNITS = 2  # FMA pipes per core: Intel since Haswell (client, most Xeons), AMD Zen 2-5
ASSUMED_GHZ = 3.0  # where neither /proc/cpuinfo nor cpufreq shows a clock


@dataclass
class Peak:
    """A core's peak float32 rate: ``lanes`` x ``units`` x 2 (a fused multiply-add is 2
    operations) x ``ghz``; ``why`` says where each came from."""

    lanes: int  # float32 lanes of one FMA unit
    units: int
    ghz: float
    why: str

    @property
    def gflop_per_s(self) -> float:
        return self.lanes * self.units * 2 * self.ghz


def core_peak(cpuinfo: str, max_khz: str | None, ghz: float | None, units: int) -> Peak:
    """The peak of one core from ``/proc/cpuinfo``'s text and cpufreq's
    ``cpuinfo_max_freq`` (kHz, or None). The vector width comes from the flags: AVX-512
    (512 bits; 256 on AMD before Zen 5 - family 0x1A - whose AVX-512 instructions run on
    256-bit FMA pipes), AVX2 with FMA (256), else 128 (SSE, NEON). The clock: ``ghz`` if
    given, else cpufreq's maximum (the boost clock), else ``cpu MHz`` (in a VM, the clock
    the hypervisor reports), else :data:`ASSUMED_GHZ`."""
    field = dict(
        (key.strip(), value.strip())
        for key, _, value in (line.partition(":") for line in cpuinfo.splitlines())
        if key.strip() and value
    )
    flags = set((field.get("flags") or field.get("Features") or "").split())
    amd_before_zen5 = (
        field.get("vendor_id") == "AuthenticAMD" and int(field.get("cpu family", "0")) < 0x1A
    )
    if "avx512f" in flags and not amd_before_zen5:
        bits, width = 512, "AVX-512"
    elif "avx512f" in flags:
        bits, width = 256, "AVX-512 on 256-bit FMA pipes (AMD before Zen 5)"
    elif {"avx2", "fma"} <= flags:
        bits, width = 256, "AVX2 + FMA"
    else:
        bits, width = 128, "128-bit vectors (no AVX2 FMA flag)"
    if ghz is not None:
        clock = f"{ghz:.3f} GHz (--ghz)"
    elif max_khz:
        ghz = int(max_khz) / 1e6
        clock = f"{ghz:.3f} GHz (cpufreq's maximum)"
    elif "cpu MHz" in field:
        ghz = float(field["cpu MHz"]) / 1e3
        clock = (
            f"{ghz:.3f} GHz (/proc/cpuinfo 'cpu MHz'; no cpufreq maximum visible, as in a VM: "
            "assumed to be the core's clock - a core that boosts above it peaks higher, "
            "pass --ghz)"
        )
    else:
        ghz = ASSUMED_GHZ
        clock = f"{ghz:.3f} GHz (ASSUMED: no clock visible; pass --ghz)"
    model = field.get("model name", platform.machine())
    why = (
        f"{model}: {width}, {bits // 32} float32 lanes x {units} FMA units (assumed: "
        f"--fma-units) x 2 x {clock}"
    )
    return Peak(bits // 32, units, ghz, why)


def read(path: str) -> str | None:
    try:
        return Path(path).read_text()
    except OSError:
        return None


def per_image(model, x) -> tuple[float, float, float]:
    """One image's forward count, training count (fedlgr's: counted, and cached for the
    round, by ``flops_per_sample``) and torch's own training count, for batch ``x``."""
    import torch  # lazy: after tune_allocator, as every torch import of this script
    from torch.utils.flop_counter import FlopCounterMode

    from fedlgr.core.client.training import flops_per_sample
    from fedlgr.core.meters.flops import flop_counter

    training = flops_per_sample(model, x)
    ghost, meta_x = copy.deepcopy(model).to("meta"), torch.empty_like(x, device="meta")
    with flop_counter() as counter:
        ghost(meta_x)
    forward = counter.get_total_flops() / len(x)
    with FlopCounterMode(display=False) as counter:
        ghost(meta_x).float().sum().backward()
    return forward, training, counter.get_total_flops() / len(x)


def one_round(scenes: int, size: int) -> tuple[dict, tuple[float, float, float], float, int]:
    """Client 0 of the demo trains one round on ``scenes`` synthetic scenes at ``size`` px:
    its figures, :func:`per_image`'s counts (made before the round), the process's CPU
    seconds over the round, and the batch size."""
    import torch  # lazy: after tune_allocator

    from fedlgr.core.client.side import ClientSide
    from fedlgr.core.messages import RoundPlan, TrainIns
    from fedlgr.shell.config import load_config
    from fedlgr.shell.data.dataset import load_scenes
    from fedlgr.shell.data.splits import make_split
    from fedlgr.shell.data.synth import synthesize

    with tempfile.TemporaryDirectory() as tmp:
        synthesize(Path(tmp) / "synth", scenes, seed=0, size=size)
        overrides = [
            f"data.path={tmp}/synth",
            f"data.cache_dir={tmp}/cache",
            f"data.image_size={size}",
            "federated.rounds=1",
            "runtime.threads=1",
            "runtime.concurrency=sequential",
            "tracking.enabled=false",
        ]
        config = load_config(REPO / "conf" / "experiment" / "demo.yaml", overrides)
        data = load_scenes(config.data)
        side = ClientSide(
            config, data, make_split(data.table, config.data), [0], torch.device("cpu")
        )
        batch = config.train.batch_size
        counts = per_image(side.clients[0].model.train(), torch.empty(batch, 3, size, size))
        start = time.process_time()
        [trained] = side.train(TrainIns(RoundPlan(1, 0, True, True)))
        cpu_s = time.process_time() - start
    return trained.figures, counts, cpu_s, batch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=1000, help="synthetic scenes (the demo's)")
    parser.add_argument("--size", type=int, default=128, help="image size (px)")
    parser.add_argument("--ghz", type=float, default=None, help="the core's clock, if known")
    parser.add_argument("--fma-units", type=int, default=FMA_UNITS, help="FMA pipes per core")
    args = parser.parse_args(argv)

    from fedlgr.shell.machine import tune_allocator

    tuned = tune_allocator()  # before torch allocates: what a fedlgr run does
    import torch

    torch.set_num_threads(1)
    peak = core_peak(
        read("/proc/cpuinfo") or "",
        (read("/sys/devices/system/cpu/cpu0/cpufreq/cpuinfo_max_freq") or "").strip() or None,
        args.ghz,
        args.fma_units,
    )
    trained, (forward, training, torch_training), cpu_s, batch = one_round(args.scenes, args.size)
    gflop, samples = trained["cost/gflops"], trained["train/samples"]
    rate = gflop / cpu_s
    print(
        f"fedlgr GFLOP per CPU-second - {date.today()} - {platform.machine()}, torch "
        f"{torch.__version__}, 1 thread, allocator tuning {'on' if tuned else 'off'}"
    )
    print(
        f"one round of client 0 of conf/experiment/demo.yaml: {args.scenes} synthetic scenes "
        f"at {args.size} px, half-width MobileNetV2, batch {batch}, {samples:.0f} samples"
    )
    print(f"per image: forward {forward / 1e9:.4f} GFLOP, training {training / 1e9:.4f} GFLOP")
    print(f"  ({training / forward:.2f}x forward; torch's own count: {torch_training / 1e9:.4f})")
    print(f"peak: {peak.why}")
    figures = {
        "round_gflop": gflop,
        "round_cpu_s": cpu_s,
        "fedlgr_cpu_s": trained["cost/cpu_s"],
        "gflop_per_cpu_s": rate,
        "peak_gflop_per_s": peak.gflop_per_s,
        "share_of_peak": rate / peak.gflop_per_s,
        "torch_gflop_per_cpu_s": torch_training * samples / 1e9 / cpu_s,
    }
    failed = report(figures, {"share_of_peak": (1.0, "max")})
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
