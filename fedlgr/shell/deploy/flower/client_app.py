"""The ClientApp a robot's SuperNode starts for each message: thin (no torch), it hands the message
to the robot service (:mod:`.service`); in a SecAgg+ round ``secaggplus_mod`` masks the reply."""

from __future__ import annotations

from flwr.app import Context, Message
from flwr.client.mod import secaggplus_mod
from flwr.clientapp import ClientApp
from flwr.clientapp.typing import ClientAppCallable
from flwr.common.secure_aggregation.secaggplus_constants import RECORD_KEY_CONFIGS

from fedlgr.shell.deploy.flower import service

app = ClientApp()


def _reply(kind: str, msg: Message, context: Context) -> Message:
    check_slot(dict(context.node_config), msg.content)
    content = service.ask(kind, context.run_id, dict(context.node_config), msg.content)
    return Message(content, reply_to=msg)


def check_slot(node_config: dict, content) -> None:
    """Refuse, before the robot service starts or reads anything, a run whose roster gives
    this robot another client than its SuperNode expects (``--client``)."""
    plan = content.config_records["plan"]
    claimed = node_config.get("client")
    if "client" in plan and claimed is not None and int(claimed) != int(plan["client"]):
        raise ValueError(
            f"this robot's SuperNode says --client {claimed}, and the run's roster gives its "
            f"key client {plan['client']}: restart it with --client {plan['client']} (or "
            "none), or fix the roster"
        )


def secure_mod(msg: Message, context: Context, call_next: ClientAppCallable) -> Message:
    """Flower's ``secaggplus_mod`` for a SecAgg+ round's messages (they carry its record); any other
    message goes to the robot unchanged, since the mod would refuse a train message without it."""
    if RECORD_KEY_CONFIGS in msg.content.config_records:
        return secaggplus_mod(msg, context, call_next)
    return call_next(msg, context)


@app.train(mods=[secure_mod])
def train(msg: Message, context: Context) -> Message:
    return _reply("train", msg, context)


@app.evaluate()
def evaluate(msg: Message, context: Context) -> Message:
    return _reply("evaluate", msg, context)
