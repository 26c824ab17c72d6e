"""2-D image operations on colour / depth arrays: no cameras, no scenes.

Each module holds a reference and its fast path: Telea inpainting (``inpaint``), pull-push interpolation
(``pushpull``), the Gaussian filter (``gaussian``), depth-aware 2x2 pooling (``pool``), and the torch versions of
pull-push and the Gaussian (``torch_ops``, the only module that imports torch)."""
