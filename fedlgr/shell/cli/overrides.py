"""A command line's ``key=value`` overrides, checked before any verb runs: a setting given
twice with two values, or ``--tracking-uri`` beside another ``tracking.uri=``, is refused,
since only the last would count and the other would be dropped without a word."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from fedlgr.errors import FedlgrError
from fedlgr.shell.tracking.uri import mask_password


def check_repeats(args: SimpleNamespace) -> None:
    """Refuse a setting given twice with two values, or ``--tracking-uri`` with another
    ``tracking.uri=``; one value spelled twice passes. A sweep's workers, given both by the
    sweep, are not checked."""
    given: dict[str, tuple[str, object]] = {}
    for item in getattr(args, "items", None) or getattr(args, "overrides", None) or []:
        key, is_override, text = item.partition("=")
        if not is_override:
            continue
        key, value = key.strip(), _value(text)
        if key in given and not _same(key, given[key][1], value):
            first, second = mask_password(given[key][0]), mask_password(item)
            raise FedlgrError(
                f"command line: {first!r} and {second!r} both set {key}; give one of them"
            )
        given.setdefault(key, (item, value))
    uri = getattr(args, "tracking_uri", None)
    override, value = given.get("tracking.uri", (None, None))
    worker = getattr(args, "worker_id", 0)
    if uri and value is not None and not worker and not _same("tracking.uri", uri, value):
        raise FedlgrError(
            f"command line: --tracking-uri {mask_password(uri)} and "
            f"{mask_password(override)!r} name two tracking stores; give one of them"
        )


def _value(text: str) -> object:
    """An override's value as OmegaConf reads it (``01`` is 1, `` x`` is ``x``)."""
    from omegaconf import OmegaConf  # lazy: omegaconf, only when a verb runs

    try:
        return OmegaConf.to_container(OmegaConf.from_dotlist([f"v={text}"]))["v"]
    except Exception:  # said with its reason when the config is loaded
        return text


def _same(key: str, first: object, second: object) -> bool:
    """Whether two values of ``key`` are one: equal, or one sqlite file by two paths."""
    if first == second:
        return True
    if key == "tracking.uri" and isinstance(first, str) and isinstance(second, str):
        paths = [
            u.removeprefix("sqlite:///") for u in (first, second) if u.startswith("sqlite:///")
        ]
        return len(paths) == 2 and Path(paths[0]).resolve() == Path(paths[1]).resolve()
    return False
