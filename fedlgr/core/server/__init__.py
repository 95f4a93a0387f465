"""The server side: what runs on the aggregating machine.

``side`` (:class:`ServerSide`: the global tensors, aggregation with the strategy's server
step, the round's record), ``aggregate`` (sample-weighted sums and means in float64) and
``evaluate`` (the server scoring the global model, ``federated.server_eval``). Nothing
here imports ``fedlgr.core.client``: the two sides meet only through
``fedlgr.core.messages`` (tests/test_layout.py checks it).
"""
