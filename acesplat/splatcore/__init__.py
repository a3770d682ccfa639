"""Torch-free splat core shared by Stage 2, the export and the edge: which SCR cells become Gaussians, and where.

validity (trusted cells), pixel_coords (their depths at pixel resolution), fusion (one layer per surface across
views), lattice (which pixels seed), seeding (the analytic start), head_io (the init head's prior and residuals),
prune (transparency and the cap), bundle_section (the Gaussian models' names in a bundle).
"""
