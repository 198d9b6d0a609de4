"""Options of the synthetic subject generator (``tools/make_subjects.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from torchfit.errors import ConfigError

__all__ = ["SynthConfig"]


@dataclass
class SynthConfig:
    """Options of ``tools/make_subjects.py`` (YAML keys, checked by ``load_config``)."""

    image_size: list[int] = field(default_factory=lambda: [720, 576])  # [width, height]
    background_frames: int = 5
    stereo: bool = True
    joint_noise_deg: float = 10.0
    floor_offset_m: float = 0.05
    yaw_deg: float = 5.0
    lean_deg: float = 2.0
    height_range_m: list[float] = field(default_factory=lambda: [1.50, 2.00])
    camera_distance_m: list[float] = field(default_factory=lambda: [3.0, 4.0])
    camera_height_m: list[float] = field(default_factory=lambda: [1.2, 1.45])
    stereo_baseline_m: list[float] = field(default_factory=lambda: [0.2, 0.3])
    noise_sigma: float = 2.0  # sensor noise, 8-bit grey levels
    illumination_change: float = 0.04  # posture images vs background: gain within +-this
    png_compression: int = 3
    # Hard rooms (configs/synth_hard.yaml), each condition on its own; all off by default, and
    # then the subjects are bit-identical to those made before these keys existed. Their random
    # draws come from separate streams, so switching one leaves everything else as it was.
    wall_shadows: bool = False  # light low and to the side, back wall close, shadow map
    furniture: bool = False  # bookshelf (book spines), door, cabinet beside the person
    textures: bool = False  # patterned walls (stripes, checks, wallpaper) and posters
    exposure_change: float = 0.0  # per posture image: common gain within +-this
    white_balance: float = 0.0  # per posture image: per-channel gain within +-this
    exposure_drift: float = 0.0  # per-channel gain drift reaching +-this at the end
    jpeg_quality: list[int] = field(default_factory=list)  # [low, high]: JPEG round trip
    # a green-screen studio (configs/synth_greenscreen.yaml, torchfit.synth.greenscreen):
    # green walls and floor, nothing on them, no green clothes, and the screen's light
    # spilling onto the person's edge (spill: the share of the screen's green added on the
    # edge itself)
    green_screen: bool = False
    spill: float = 0.0

    def __post_init__(self) -> None:
        if len(self.image_size) != 2 or min(self.image_size) < 16:
            raise ConfigError(
                f"synth config: key 'image_size' expects [width, height], got {self.image_size}"
            )
        for key in ("height_range_m", "camera_distance_m", "camera_height_m", "stereo_baseline_m"):
            value = getattr(self, key)
            if len(value) != 2 or value[0] > value[1]:
                raise ConfigError(f"synth config: key '{key}' expects [low, high], got {value}")
        if self.background_frames < 5:
            raise ConfigError(
                f"synth config: key 'background_frames' must be >= 5, got {self.background_frames}"
            )
        if self.jpeg_quality and (
            len(self.jpeg_quality) != 2
            or not 1 <= self.jpeg_quality[0] <= self.jpeg_quality[1] <= 100
        ):
            raise ConfigError(
                "synth config: key 'jpeg_quality' expects [] or [low, high] within 1..100, "
                f"got {self.jpeg_quality}"
            )
        for key in ("exposure_change", "white_balance", "exposure_drift"):
            if not 0.0 <= getattr(self, key) < 0.5:
                raise ConfigError(
                    f"synth config: key '{key}' must be in [0, 0.5), got {getattr(self, key)}"
                )
        if not 0.0 <= self.spill <= 1.0:
            raise ConfigError(f"synth config: key 'spill' must be in [0, 1], got {self.spill}")
        if not 0 <= self.png_compression <= 9:
            raise ConfigError(
                f"synth config: key 'png_compression' must be in 0..9, got {self.png_compression}"
            )
