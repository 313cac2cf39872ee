"""LaTeX text escaping shared by the table writers."""

from __future__ import annotations


def tex_escape(s: str) -> str:
    """``s`` safe inside a LaTeX table cell (``<=`` as a math symbol)."""
    return (
        s.replace("\\", r"\textbackslash{}")
        .replace("&", r"\&")
        .replace("%", r"\%")
        .replace("_", r"\_")
        .replace("#", r"\#")
        .replace("<=", r"$\leq$")
        .replace("@", "@")
    )
