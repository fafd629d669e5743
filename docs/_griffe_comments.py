"""Griffe extension of the API reference (mkdocs.yml: mkdocstrings' `extensions:`): the
`#:` comment lines right above a module or class attribute become its docstring, so the
constants the code documents that way (`pmsmjax.LOCK_DEG`, `pmsmjax.runtime.SAFE_FLAGS`,
...) appear in the reference with their meaning."""

from __future__ import annotations

import griffe


class CommentDocstrings(griffe.Extension):
    def on_attribute_instance(self, *, node, attr, agent, **kwargs) -> None:
        code = getattr(agent, "code", None)
        if attr.docstring is not None or not code or not attr.lineno:
            return
        lines = code.splitlines()
        comment: list[str] = []
        i = attr.lineno - 2  # the line above the assignment (0-based)
        while i >= 0 and lines[i].strip().startswith("#:"):
            comment.insert(0, lines[i].strip()[2:].strip())
            i -= 1
        if comment:
            attr.docstring = griffe.Docstring("\n".join(comment), parent=attr)
