"""fedlgr on Flower's Deployment Runtime: the ServerApp (:mod:`.server_app`) on a SuperLink, the
ClientApp (:mod:`.client_app`) on each robot's SuperNode; docs/deployment.md has the commands."""

from pathlib import Path

APP_DIR = Path(__file__).parent / "app"  # the Flower app (pyproject.toml) for `flwr run`
