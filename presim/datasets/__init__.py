"""6D-pose datasets in BOP format (thesis §5.3.5-5.3.7): object models and sources, camera sampling
around targets, annotation (masks, boxes, visibility), the BOP writer and reader, the generation job
(local processes or Ray) and a validator. See docs/datasets.md.

Modules are imported on demand (``from presim.datasets.generate import generate_bop``) so that
``import presim.datasets`` stays cheap.
"""
