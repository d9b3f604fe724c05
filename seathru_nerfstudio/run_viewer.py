"""``ns-viewer`` that listens on loopback unless told otherwise.

nerfstudio 1.1.5's ``ns-viewer`` does not use the viewer settings saved with a run: it replaces
them with its own command-line ``--viewer.*`` options, whose host defaults to ``0.0.0.0`` (every
interface), so ``ns-viewer --load-config .../config.yml`` on one of our runs would be reachable
from the network. This is the same command (nerfstudio's ``RunViewer``, same options) with one
default changed, ``--viewer.websocket-host 127.0.0.1``::

    python -m seathru_nerfstudio.run_viewer --load-config outputs/.../config.yml
    python -m seathru_nerfstudio.run_viewer --load-config ... --viewer.websocket-host 0.0.0.0  # opt in

With nerfstudio's own command, pass the host yourself:
``ns-viewer --load-config ... --viewer.websocket-host 127.0.0.1``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import tyro

from nerfstudio.scripts.viewer.run_viewer import RunViewer, ViewerConfigWithoutNumRays

from seathru_nerfstudio.config import LOOPBACK  # what ns-train uses for our methods


@dataclass
class LoopbackViewerConfig(ViewerConfigWithoutNumRays):
    """nerfstudio's ``ns-viewer`` options, listening on loopback by default."""

    websocket_host: str = LOOPBACK
    """The host address to bind the websocket server to (``0.0.0.0``: every interface)."""


@dataclass
class RunLoopbackViewer(RunViewer):
    """Load a checkpoint and start the viewer, on 127.0.0.1 unless ``--viewer.websocket-host`` says otherwise."""

    viewer: LoopbackViewerConfig = field(default_factory=LoopbackViewerConfig)
    """Viewer configuration"""


def entrypoint() -> None:
    """As nerfstudio's ``ns-viewer`` entry point, with :class:`RunLoopbackViewer`."""
    tyro.extras.set_accent_color("bright_yellow")
    tyro.cli(tyro.conf.FlagConversionOff[RunLoopbackViewer]).main()


if __name__ == "__main__":
    entrypoint()
