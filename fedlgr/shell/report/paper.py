"""The paper's published Tables I and II (Churamani et al. 2024, arXiv:2405.15773, on
MANNERS-DB) as printed, added under each method's row by ``fedlgr report --paper``."""

from __future__ import annotations

from fedlgr.shell.report.tables import Cell, Table

CITATION = "Churamani et al. 2024, arXiv:2405.15773"
SUFFIX = " (paper)"
# The paper's score columns, in its order: not metrics.SCORES, as they copy what it printed.
SCORES = ("loss", "rmse", "pcc")
CLIENTS = (2, 10)

# Table I, a row per augmentation (W/O, W/) and method: loss, RMSE, PCC for 2 clients, then
# for 10 clients.
TABLE1 = """
W/O FedAvg                0.264 0.510 0.508 0.220 0.467 0.487
W/O FedBN                 0.310 0.553 0.486 0.226 0.471 0.486
W/O FedProx               0.262 0.507 0.513 0.211 0.459 0.517
W/O FedOpt                0.245 0.492 0.501 0.210 0.458 0.492
W/O FedDistill            0.276 0.522 0.475 0.233 0.481 0.470
W/O FedRootAvg            0.276 0.522 0.482 0.231 0.477 0.459
W/O FedRootBN             0.272 0.518 0.498 0.263 0.510 0.420
W/O FedRootProx           0.264 0.511 0.481 0.240 0.486 0.447
W/O FedRootOpt            0.285 0.530 0.473 0.240 0.486 0.460
W/O FedRootDistill        0.294 0.539 0.489 0.305 0.550 0.363
W/  FedAvg                0.192 0.435 0.547 0.178 0.420 0.586
W/  FedBN                 0.205 0.447 0.554 0.188 0.429 0.567
W/  FedProx               0.208 0.451 0.536 0.173 0.412 0.581
W/  FedOpt                0.204 0.450 0.506 0.177 0.420 0.568
W/  FedDistill            0.221 0.468 0.538 0.205 0.449 0.560
W/  FedRootAvg            0.192 0.433 0.547 0.198 0.440 0.563
W/  FedRootBN             0.197 0.442 0.558 0.194 0.439 0.539
W/  FedRootProx           0.186 0.427 0.541 0.196 0.439 0.552
W/  FedRootOpt            0.190 0.432 0.528 0.206 0.450 0.549
W/  FedRootDistill        0.225 0.469 0.525 0.222 0.465 0.539
"""

# Table II, as Table I: loss, RMSE, PCC after Task 1, then after Task 2, for 2 clients, then
# the same for 10 clients.
TABLE2 = """
W/O FedAvg-EWC            0.705 0.826 0.488 0.911 0.944 0.347 0.364 0.591 0.325 0.393 0.617 0.278
W/O FedAvg-EWCOnline      0.488 0.685 0.469 0.381 0.608 0.384 0.328 0.566 0.373 0.359 0.589 0.321
W/O FedAvg-MAS            0.568 0.740 0.570 0.363 0.597 0.357 0.421 0.641 0.494 0.464 0.674 0.357
W/O FedAvg-SI             0.488 0.686 0.571 0.675 0.811 0.343 0.451 0.665 0.323 0.376 0.598 0.306
W/O FedAvg-NR             0.403 0.634 0.491 0.296 0.538 0.333 0.376 0.600 0.447 0.408 0.628 0.341
W/O FedRoot-EWC           0.433 0.652 0.472 0.998 0.963 0.382 9.320 3.050 0.336 8.950 2.990 0.335
W/O FedRoot-EWCOnline     0.614 0.778 0.436 0.447 0.659 0.400 9.170 3.030 0.330 9.560 3.090 0.376
W/O FedRoot-MAS           0.397 0.627 0.429 0.569 0.740 0.422 8.860 2.980 0.363 8.750 2.960 0.369
W/O FedRoot-SI            0.968 0.984 0.441 0.840 0.893 0.418 9.360 3.060 0.417 9.120 3.020 0.369
W/O FedRoot-NR            0.762 0.870 0.325 0.287 0.533 0.444 0.446 0.656 0.462 0.482 0.677 0.339
W/O FedLGR                0.252 0.499 0.599 0.465 0.677 0.534 0.299 0.539 0.515 0.320 0.553 0.421
W/  FedAvg-EWC            0.669 0.807 0.420 0.348 0.584 0.395 0.397 0.624 0.472 0.433 0.653 0.456
W/  FedAvg-EWCOnline      0.495 0.702 0.438 0.629 0.788 0.376 0.319 0.561 0.365 0.329 0.579 0.363
W/  FedAvg-MAS            0.267 0.514 0.601 0.665 0.814 0.394 0.343 0.580 0.480 0.354 0.587 0.328
W/  FedAvg-SI             0.280 0.526 0.546 0.328 0.568 0.444 0.471 0.682 0.418 0.435 0.654 0.426
W/  FedAvg-NR             0.450 0.669 0.531 0.710 0.839 0.451 0.392 0.618 0.425 0.490 0.698 0.368
W/  FedRoot-EWC           0.736 0.836 0.529 0.327 0.569 0.463 0.441 0.648 0.543 0.449 0.655 0.467
W/  FedRoot-EWCOnline     0.517 0.712 0.398 0.446 0.661 0.363 0.688 0.805 0.446 0.612 0.761 0.405
W/  FedRoot-MAS           0.265 0.511 0.492 0.616 0.782 0.436 0.797 0.851 0.542 1.030 0.930 0.439
W/  FedRoot-SI            0.388 0.596 0.405 0.735 0.821 0.478 0.481 0.688 0.323 0.521 0.708 0.439
W/  FedRoot-NR            0.781 0.875 0.491 0.368 0.604 0.354 0.539 0.728 0.268 0.409 0.635 0.447
W/  FedLGR                0.230 0.478 0.531 0.493 0.699 0.479 0.288 0.528 0.563 0.317 0.560 0.482
"""


def paper_values() -> dict[tuple[str, bool, str, str], float]:
    """(table, augmented, method, column key) -> the paper's value, the column keys as the
    report's (``2c/test/rmse``, ``10c/after_task2/test/pcc``)."""
    out = {}
    for name, text, stages in (
        ("table1", TABLE1, ("",)),
        ("table2", TABLE2, ("after_task1/", "after_task2/")),
    ):
        keys = [f"{c}c/{t}test/{s}" for c in CLIENTS for t in stages for s in SCORES]
        for augmentation, method, *values in map(str.split, text.strip().splitlines()):
            row = zip(keys, map(float, values), strict=True)
            out |= {(name, augmentation == "W/", method, k): v for k, v in row}
    return out


def with_paper(table: Table) -> Table:
    """``table`` (Table I or II) with the paper's row under each of its methods that the
    paper has, and a note saying what they are; other tables as they are."""
    if table.name not in ("table1", "table2"):
        return table
    values = paper_values()
    for block in table.blocks:
        augmented = block.title.startswith("W/ ")
        rows = []
        for method, cells in block.rows:
            rows.append((method, cells))
            if not any((table.name, augmented, method, c.key) in values for c in table.columns):
                continue  # a method the paper has not (LwF, FedMedian, a DP run)
            paper = [
                Cell(values.get((table.name, augmented, method, c.key)), cells[i].decimals)
                for i, c in enumerate(table.columns)
            ]
            rows.append((method + SUFFIX, paper))
        block.rows = rows
    table.notes.append(
        f"Rows marked *{SUFFIX.strip()}* are the paper's published values ({CITATION}, "
        f"Table {table.number}, on MANNERS-DB, as printed; no CCC), not runs: they are "
        "not marked best, and runs on other data (the synthetic living room) are not "
        "comparable to them in value."
    )
    return table
