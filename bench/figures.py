"""Printing benchmark figures against their targets (shared by the bench scripts)."""

from __future__ import annotations


def report(figures: dict[str, float], targets: dict[str, tuple[float, str]]) -> int:
    """Print each figure, with its target where it has one; return how many were missed.

    ``targets`` maps a figure to ``(limit, "max" | "min")``.
    """
    missed = 0
    for name, value in figures.items():
        verdict = ""
        if name in targets:
            limit, kind = targets[name]
            ok = value <= limit if kind == "max" else value >= limit
            missed += not ok
            verdict = f"  ({'<=' if kind == 'max' else '>='} {limit:g}: {'ok' if ok else 'MISSED'})"
        print(f"  {name:<24}{value:10.2f}{verdict}")
    return missed
