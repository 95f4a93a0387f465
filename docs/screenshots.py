"""Screenshots of what a researcher sees of the demo's runs in the MLflow UI (docs/tracking.md).

``fedlgr demo`` (FedAvg and FedRootAvg on the synthetic living room, 1000 scenes at 128 px,
system metrics on; ``--rounds`` of its 9, ~25 s each on 2 cores) logs to a fresh store; a
real ``mlflow server`` serves it, and headless Chromium photographs the runs table, a run's
page and its model-metrics tab, the chart view and the compare view of the runs:

    uv run python docs/screenshots.py docs/img/mlflow/after --rounds 4

Needs Debian's Chromium (``apt-get install chromium``); downloads nothing.
"""

from __future__ import annotations

import argparse
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

from fedlgr.shell.tracking.store import runs_link

EXPERIMENT = "demo"  # conf/experiment/demo.yaml's
CHROMIUM_FLAGS = [  # as the machine notes start it: no sandbox as root, no Google hosts
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--virtual-time-budget=20000",  # let the UI's JavaScript fetch and render the runs
]


def fedlgr(*args: str, cwd: Path) -> None:
    subprocess.run([sys.executable, "-m", "fedlgr", *args], cwd=cwd, check=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(store: str, artifacts: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    command = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", store]
    command += ["--artifacts-destination", str(artifacts), "--host", "127.0.0.1"]
    command += ["--port", str(port), "--workers", "1"]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=2):
                return process, url
        except OSError:
            time.sleep(0.5)
    process.kill()
    raise SystemExit("mlflow server did not answer /health within 120 s")


def search(url: str, experiment_id: str) -> list[dict]:
    body = json.dumps({"experiment_ids": [experiment_id], "max_results": 100}).encode()
    request = urllib.request.Request(
        f"{url}/api/2.0/mlflow/runs/search", body, {"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(request, timeout=30) as answer:
        return json.load(answer)["runs"]


def shoot(chromium: str, page: str, out: Path, profile: Path, size: str) -> None:
    command = [chromium, *CHROMIUM_FLAGS, f"--window-size={size}", f"--screenshot={out}"]
    command.append(f"--user-data-dir={profile}")
    subprocess.run([*command, page], check=True, capture_output=True, timeout=180)
    print(f"{out}  <- {page}")


def pages(url: str, experiment_id: str, runs: list[dict]) -> dict[str, str]:
    """The views to photograph, by file name."""
    trials = sorted(runs, key=lambda r: r["info"]["run_name"])
    trial = trials[0]["info"]["run_id"]
    base = f"{url}/#/experiments/{experiment_id}"
    ids = json.dumps([r["info"]["run_id"] for r in trials])
    compare = urllib.parse.urlencode({"runs": ids, "experiments": json.dumps([experiment_id])})
    link = runs_link(url, experiment_id)  # the link fedlgr prints
    return {
        "runs-table.png": link,
        "run-page.png": f"{base}/runs/{trial}",
        "run-metrics.png": f"{base}/runs/{trial}/model-metrics",
        "chart-view.png": f"{link}&compareRunsMode=CHART",
        "compare-view.png": f"{url}/#/compare-runs?{compare}",
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="folder for the PNG files")
    parser.add_argument(
        "--work", type=Path, help="keep the data and store here (a second call reuses them)"
    )
    parser.add_argument("--size", default="1920,1080", help="window size (default: 1920,1080)")
    parser.add_argument("--rounds", type=int, default=9, help="the demo's rounds (default: 9)")
    args = parser.parse_args(argv)
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("no Chromium here: apt-get install chromium")
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="fedlgr-screens-") as tmp:
        work = (args.work or Path(tmp)).resolve()
        work.mkdir(parents=True, exist_ok=True)
        store = f"sqlite:///{work}/mlflow.db"
        if not (work / "mlflow.db").exists():
            rounds = f"federated.rounds={args.rounds}"
            fedlgr("demo", "--data", "synth", "--tracking-uri", store, rounds, cwd=work)
        server, url = start_server(store, work / "artifacts")
        try:
            experiment = urllib.parse.urlencode({"experiment_name": EXPERIMENT})
            with urllib.request.urlopen(
                f"{url}/api/2.0/mlflow/experiments/get-by-name?{experiment}", timeout=30
            ) as answer:
                experiment_id = json.load(answer)["experiment"]["experiment_id"]
            for name, page in pages(url, experiment_id, search(url, experiment_id)).items():
                shoot(chromium, page, args.out / name, work / "profile", args.size)
        finally:
            server.terminate()
            server.wait(timeout=60)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
