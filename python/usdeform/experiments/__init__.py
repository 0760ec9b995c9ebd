"""Experiments that reproduce the paper's results on the simulator (``usdeform experiment ...``)."""
