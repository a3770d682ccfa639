"""The applications: the `acesplat` and `acesplat-edge` programs and the demo, thin over library calls.

The top floor: it may import every package; nothing imports it.
"""
