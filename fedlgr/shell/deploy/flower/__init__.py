"""fedlgr on Flower's Deployment Runtime: a SuperLink running the ServerApp (:mod:`.server_app`),
one SuperNode per robot running the ClientApp (:mod:`.client_app`), and ``flwr run`` of the app in
``APP_DIR``. docs/deployment.md has the commands."""

from pathlib import Path

APP_DIR = Path(__file__).parent / "app"  # the Flower app (pyproject.toml) for `flwr run`
