"""Whole-image outputs that are computed when they are first read.

nerfstudio's viewer, ``ns-render`` and ``ns-eval`` ask a model for every output of an image
(``get_outputs_for_camera``) and then read one or a few of them: the viewer the output chosen in
its panel and ``depth``, ``ns-render`` the ``--rendered-output-names``. A SeaThru image has
twenty outputs; rendering them all to show one wastes most of the work (the medium network on
every ray for a ``clean`` view, the object field for a map of the medium, the tone mapping of
nine display outputs). :class:`LazyOutputs` lists every name at once and computes a value only
when it is read, by a callback that may compute several at once (everything one pass over the
object field yields), and keeps what it computed.
"""

from __future__ import annotations

from typing import Callable, Dict, Iterator, List, MutableMapping, Sequence

from torch import Tensor

Compute = Callable[[str, "LazyOutputs"], Dict[str, Tensor]]
"""``compute(name, outputs)``: the value of ``name``, and any others computed on the way; it may
read other outputs through ``outputs`` (a display output reads its linear source)."""


class LazyOutputs(MutableMapping[str, Tensor]):
    """A mapping of output names to images whose values are computed on first read.

    ``keys()``, ``in`` and ``len`` compute nothing. Values that callers set (the viewer adds its
    own, e.g. ``gl_z_buf_depth``) are kept as in a dict.
    """

    def __init__(self, names: Sequence[str], compute: Compute) -> None:
        self._names: List[str] = list(dict.fromkeys(names))
        self._values: Dict[str, Tensor] = {}
        self._compute = compute

    def __getitem__(self, name: str) -> Tensor:
        if name not in self._values:
            if name not in self._names:
                raise KeyError(name)
            computed = self._compute(name, self)
            self._values.update({key: value for key, value in computed.items() if key not in self._values})
        return self._values[name]

    def __setitem__(self, name: str, value: Tensor) -> None:
        if name not in self._names:
            self._names.append(name)
        self._values[name] = value

    def __delitem__(self, name: str) -> None:
        self._names.remove(name)
        self._values.pop(name, None)

    def __contains__(self, name: object) -> bool:  # Mapping's would compute the value
        return name in self._names

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._names))

    def __len__(self) -> int:
        return len(self._names)

    def computed(self) -> List[str]:
        """The names whose values exist (computed or set), in the mapping's order."""
        return [name for name in self._names if name in self._values]

    def __repr__(self) -> str:
        return f"LazyOutputs({len(self._names)} outputs, computed: {self.computed()})"
