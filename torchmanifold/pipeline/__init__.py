"""Progressive video rendering: bandwidth schedule, frame denoising, the progressive loop, the render job."""
from torchmanifold.pipeline.denoise import DenoiseSettings, Denoiser, default_guide_sigmas, denoise_frames
from torchmanifold.pipeline.schedule import DEFAULT_ALPHA, BandwidthSchedule, bandwidth_factor, bandwidth_factors

__all__ = [
    "DenoiseSettings", "Denoiser", "denoise_frames", "default_guide_sigmas",
    "DEFAULT_ALPHA", "BandwidthSchedule", "bandwidth_factor", "bandwidth_factors",
]
