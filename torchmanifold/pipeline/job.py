"""The render job and the ``denoise`` command under their former module, for callers that import them
from here; each lives in its own module:

- :mod:`torchmanifold.pipeline.render_job`: ``render_job``, ``moving_mask``, ``RENDER_DEFAULTS``
- :mod:`torchmanifold.pipeline.denoise_files`: ``denoise_files``
- :mod:`torchmanifold.pipeline.charts`: ``write_chart``
- :mod:`torchmanifold.pipeline.convergence`: ``spp_to_match``
- :mod:`torchmanifold.io.files`: ``prepare_out``; :mod:`torchmanifold.io.png`: ``write_png``
"""
from torchmanifold.io.files import prepare_out
from torchmanifold.pipeline.charts import write_chart
from torchmanifold.pipeline.convergence import spp_to_match
from torchmanifold.pipeline.denoise_files import denoise_files
from torchmanifold.pipeline.render_job import METHODS, RENDER_DEFAULTS, moving_mask, render_job

__all__ = ["prepare_out", "render_job", "denoise_files", "moving_mask", "spp_to_match", "write_chart",
           "RENDER_DEFAULTS", "METHODS"]
