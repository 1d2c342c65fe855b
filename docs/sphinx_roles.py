"""The package's docstrings name other objects with Sphinx roles (``:func:`~pixelmpc_jax.sim.env.make_world```); the
API reference shows each as code, as Sphinx would: by its last name after a ``~``, whole otherwise (a griffe
extension, named in mkdocs.yml)."""

import re

import griffe

ROLE = re.compile(r":(?:func|class|mod|meth|data|attr|exc|obj):`(~?)([^`]+)`")


def _as_code(match: re.Match) -> str:
    short, name = match.groups()
    return f"`{name.rsplit('.', 1)[-1] if short else name}`"


class SphinxRoles(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = ROLE.sub(_as_code, obj.docstring.value)
