"""Griffe extensions for the API pages (loaded by mkdocs.yml; nothing here is imported by lidarjax).

- :class:`RedundantAliasIsPublic`: ``from ._x import Name as Name`` makes ``Name`` public.
  That redundant alias is the house convention for a package's public surface (DESIGN.md,
  convention 1). Griffe treats imported names as private unless the module's ``__all__``
  lists them, so packages without ``__all__`` (``lidarjax.datasets``, ``lidarjax.sim``)
  would show no members. A module that defines ``__all__`` keeps it as the only rule.
- :class:`SphinxRoles`: the docstrings cross-reference with Sphinx roles
  (``:func:`fit```, ``:class:`~lidarjax.rays.RayBatch```), which Markdown would print
  literally. Each role becomes inline code that links to the object's API entry when the
  name resolves in the docstring's scope and the object is documented; otherwise it stays
  plain code (an optional cross-reference, so an unresolved one is no build warning).
"""

from __future__ import annotations

import ast
import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|exc|obj|const):`([^`]+)`")


class RedundantAliasIsPublic(griffe.Extension):
    """Mark ``from a import x as x`` aliases public in modules that define no ``__all__``."""

    def __init__(self) -> None:
        super().__init__()
        self._redundant: set[str] = set()

    def on_alias_instance(self, *, node: Any, alias: griffe.Alias, **kwargs: Any) -> None:
        if isinstance(node, ast.ImportFrom) and any(
            n.asname == n.name == alias.name for n in node.names
        ):
            self._redundant.add(alias.path)

    def on_module(self, *, mod: griffe.Module, **kwargs: Any) -> None:
        if mod.exports:  # __all__ decides
            return
        for member in mod.members.values():
            if member.is_alias and member.path in self._redundant:
                member.public = True


def _resolve(obj: griffe.Object, target: str) -> str | None:
    """Full path of ``target`` as Python would find it from ``obj``'s docstring, or None."""
    if target.startswith("."):  # relative module path: ``._office``, ``..raytrace``
        mod = obj.module
        base = mod if mod.is_init_module else mod.parent
        rest = target[1:]
        while rest.startswith(".") and base is not None:
            base, rest = base.parent, rest[1:]
        return f"{base.path}.{rest}" if base is not None and rest else None
    head, _, tail = target.partition(".")
    try:
        path = obj.resolve(head)
    except (griffe.NameResolutionError, griffe.AliasResolutionError, KeyError):
        if head == obj.package.name:  # a fully qualified name
            path = head
        else:
            return None
    return f"{path}.{tail}" if tail else path


class SphinxRoles(griffe.Extension):
    """Turn Sphinx cross-reference roles in docstrings into (optional) autorefs links."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        stack: list[griffe.Object] = [pkg]
        while stack:
            obj = stack.pop()
            doc = obj.docstring
            if doc is not None and ":" in doc.value:
                doc.value = _ROLE.sub(lambda m, obj=obj: self._link(obj, m[1]), doc.value)
            stack.extend(m for m in obj.members.values() if not m.is_alias)

    @staticmethod
    def _link(obj: griffe.Object, text: str) -> str:
        short = text.startswith("~")
        target = text.lstrip("~").removesuffix("()")
        shown = target.rsplit(".", 1)[-1] if short else target
        code = f"<code>{shown}</code>"
        path = _resolve(obj, target)
        if path is None:
            return code
        return f'<autoref identifier="{path}" optional>{code}</autoref>'
