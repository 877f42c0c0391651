"""Writing a team config back to TOML (``TeamConfig.to_toml``): scalars first, then
``[[robots]]`` with their ``[robots.camera]``, then every table, nested tables as dotted
headers."""

from __future__ import annotations

from typing import Any


def drop_none(d: dict[str, Any]) -> dict[str, Any]:
    """``d`` without its ``None`` values, recursively (TOML has no null)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if v is None:
            continue
        out[k] = drop_none(v) if isinstance(v, dict) else v
    return out


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} to TOML")


def dump_toml(d: dict[str, Any]) -> str:
    lines: list[str] = []
    scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and k != "robots"}
    for k, v in scalars.items():
        lines.append(f"{k} = {toml_value(v)}")

    def table(prefix: str, t: dict[str, Any]) -> None:
        lines.append("")
        lines.append(f"[{prefix}]")
        subtables = {}
        for k, v in t.items():
            if isinstance(v, dict):
                subtables[k] = v
            else:
                lines.append(f"{k} = {toml_value(v)}")
        for k, v in subtables.items():
            key = f'"{k}"' if "-" in k or "." in k else k
            table(f"{prefix}.{key}", v)

    for robot in d.get("robots", []):
        lines.append("")
        lines.append("[[robots]]")
        camera = robot.get("camera", {})
        for k, v in robot.items():
            if k == "tags" and v:
                tags = ", ".join(
                    f"{{ node = {toml_value(t['node'])}, lever_arm = {toml_value(t['lever_arm'])} }}"
                    for t in v
                )
                lines.append(f"tags = [{tags}]")
            elif k not in ("camera", "tags"):
                lines.append(f"{k} = {toml_value(v)}")
        lines.append("[robots.camera]")
        for k, v in camera.items():
            lines.append(f"{k} = {toml_value(v)}")
    for k, v in d.items():
        if isinstance(v, dict):
            table(k, v)
    return "\n".join(lines) + "\n"
