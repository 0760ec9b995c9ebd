"""Live scanning: correct and compound a robotic ultrasound scan as it streams in over OpenIGTLink.

``serve`` runs the service (``usdeform live``): it reads B-mode images, probe poses, contact force
and probe displacement as PLUS Server or a robot node sends them, pairs them by timestamp, corrects
each frame with a fitted model, compounds it into a volume that grows with the scan and sends the
volume and the latest corrected frame to viewers such as 3D Slicer; it records the paired frames to
a PLUS sequence file, from which ``usdeform correct --volume`` makes the same volume. ``replay``
(``usdeform replay``) plays a sequence file as PLUS Server would. Needs pyigtl (``pip install
'usdeform[live]'``).
"""

from __future__ import annotations

from .client import LiveClient
from .pairing import ScalarSource, StreamSettings
from .replay import ReplayResult, replay
from .server import LiveResult, LiveServer, OutputSettings, serve

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
