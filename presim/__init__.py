"""PreSim: a photo-realistic RGB-D simulator for robots, built from captured RGB-D images.

Data flow (one sub-package per stage)::

    capture -> depth -> synthesis -> sensors -> sim -> outputs -> datasets -> pose
"""

__version__ = "0.1.0"
