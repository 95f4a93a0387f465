"""The client side: what runs where the clients are (a client's own machine, or a
process's share of the clients in the in-process runtime).

``training`` (one client's model, optimiser, data and local training loop), ``plugins``
(the hooks strategies and continual-learning methods add to that loop), ``side``
(:class:`ClientSide`: a process's clients answering the server's messages), ``pool``
(clients trained side by side in threads) and ``stacked`` (clients trained as one stacked
model). Nothing here imports ``fedlgr.core.server``: the two sides meet only through
``fedlgr.core.messages`` (tests/test_layout.py checks it).
"""
