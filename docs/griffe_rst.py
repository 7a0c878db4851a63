"""A griffe extension for the API pages: the docstrings' reStructuredText spellings read as Markdown.

The package's docstrings are written for a reader of the source (and pydoc): Sphinx roles such as
``:class:`~stewart_calib.workflows.online.OnlineCalibrator``` and literal blocks introduced by ``::``.
mkdocstrings renders Markdown, where those show as typed. This turns a role into inline code of
its target (the last component where the target starts with ``~``, as Sphinx shows it) and a
paragraph's closing ``::`` into ``:`` (the indented block after it is already code in Markdown).
The docstrings themselves are not changed.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:mod|class|func|meth|data|attr|exc|obj|const|ref|term):`(~?)([^`]+)`")
LITERAL = re.compile(r"(?m)(\S)::$|^[ \t]*::$")


def _role(match: re.Match[str]) -> str:
    tilde, target = match.groups()
    shown = target.rsplit(".", 1)[-1] if tilde else target
    return f"`{shown}`"


def markdown(text: str) -> str:
    """``text`` with its roles as inline code and its ``::`` markers as colons."""
    text = ROLE.sub(_role, text)
    return LITERAL.sub(lambda m: f"{m.group(1)}:" if m.group(1) else "", text)


class RstToMarkdown(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown(obj.docstring.value)
