"""What the tests share, by topic; test modules import it, never each other or conftest
(tests/test_layout.py checks). Fixtures are not here: they live in tests/conftest.py.

- ``checkout``: the repository's root and the files git does not track (the session check
  that the tests leave the checkout as they found it).
- ``data``: rating CSV rows written and read.
- ``runs``: the fast-dev-run config, an in-process orchestrator of a config, a run read
  back from MLflow, an in-process Ctrl-C.
- ``processes``: ``fedlgr run`` as a real child process, its arguments and environment,
  and the one run of a store.
- ``ports``: free localhost ports, and waiting for one to listen.
- ``flower``: a real Flower federation on localhost.
- ``lgr``: tiny FedLGR clients with hand-checkable numbers, and FedLGR's fast config.
- ``float64``: float64 comparisons of batched and sequential training.
- ``sweeps``: sweep files, studies and their MLflow runs.
- ``report``: a report's Markdown tables read back.
"""
