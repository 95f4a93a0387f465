"""The ClientApp: what Flower's SuperNode starts on a robot for each message.

It is deliberately thin (no torch): it passes the message to the robot's long-lived
service (:mod:`.service`), which holds the robot's data, model and private state
(:mod:`.robot`), and sends back its reply. A failure on the robot becomes Flower's error
reply, which the server reports with the robot's message.
"""

from __future__ import annotations

from flwr.app import Context, Message
from flwr.clientapp import ClientApp

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


@app.train()
def train(msg: Message, context: Context) -> Message:
    return _reply("train", msg, context)


@app.evaluate()
def evaluate(msg: Message, context: Context) -> Message:
    return _reply("evaluate", msg, context)
