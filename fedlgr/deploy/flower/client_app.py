"""The ClientApp: what Flower's SuperNode starts on a robot for each message.

It is deliberately thin (no torch): it passes the message to the robot's long-lived
service (:mod:`.service`), which holds the robot's data, model and private state
(:mod:`.robot`), and sends back its reply. A failure on the robot becomes Flower's error
reply, which the server reports with the robot's message.
"""

from __future__ import annotations

from flwr.app import Context, Message
from flwr.clientapp import ClientApp

from fedlgr.deploy.flower import service

app = ClientApp()


def _reply(kind: str, msg: Message, context: Context) -> Message:
    content = service.ask(kind, context.run_id, dict(context.node_config), msg.content)
    return Message(content, reply_to=msg)


@app.train()
def train(msg: Message, context: Context) -> Message:
    return _reply("train", msg, context)


@app.evaluate()
def evaluate(msg: Message, context: Context) -> Message:
    return _reply("evaluate", msg, context)
