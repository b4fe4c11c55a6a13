"""Floor radio maps: Sionna RT's own ``RadioMapSolver`` on a horizontal plane
(:mod:`.radio_map`), and the figure a person reads beside it (:mod:`.figure`)."""

from .figure import cut_footprints, save_radio_map_png
from .radio_map import (RadioMap, compute_radio_map, load_radio_map, radio_map_from_gain,
                        save_radio_map)

__all__ = ["RadioMap", "compute_radio_map", "cut_footprints", "load_radio_map",
           "radio_map_from_gain", "save_radio_map", "save_radio_map_png"]
