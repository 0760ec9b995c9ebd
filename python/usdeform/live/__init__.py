"""Live scanning: correct and compound a robotic ultrasound scan as it streams in over OpenIGTLink.

``serve`` runs the service (``usdeform live``): it reads B-mode images, probe poses, contact force
and probe displacement as PLUS Server or a robot node sends them, pairs them by timestamp (each
connection on its own), corrects each frame with a fitted model and compounds it into a volume that
grows with the scan. It sends each corrected frame as soon as it is corrected, the frame as received
and the volume to viewers such as 3D Slicer, each viewer on its own queue, placed as
:mod:`usdeform.live.outputs` says; it answers Plus Remote's volume-reconstruction commands
(:mod:`usdeform.live.plus_commands`). It records the paired frames to a PLUS sequence file, from which
``usdeform correct --volume`` makes the same volume. ``replay`` (``usdeform replay``) plays a sequence
file as PLUS Server would. Needs pyigtl (``pip install 'usdeform[live]'``).
"""

from __future__ import annotations

from .client import LiveClient
from .outputs import OutputSettings
from .pairing import ScalarSource, StreamSettings
from .replay import ReplayResult, replay
from .server import LiveResult, LiveServer, serve

__all__ = [
    "LiveClient",
    "LiveResult",
    "LiveServer",
    "OutputSettings",
    "ReplayResult",
    "ScalarSource",
    "StreamSettings",
    "replay",
    "serve",
]
