"""A Python module's code, apart from its words.

What the kept models are filed under (:func:`harness.descriptors.store.code_digest`) and what the
bench compares to say whether a row's code changed (``bench/provenance.py``): a change to
docstrings, comments or layout is not a change of code.
"""

from __future__ import annotations

import ast


def code_text(source: str) -> str:
    """Python ``source`` as its code, without docstrings, comments or layout.

    Parsed and written back by :func:`ast.unparse` with every docstring left out.

    Raises:
        SyntaxError: ``source`` is not Python.
    """
    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            node.body = body[1:] or [ast.Pass()]
    return ast.unparse(tree)
