"""Keys of ``DataparserOutputs.metadata`` that this package's dataparsers write and its model reads."""

RANGE_SPREAD_KEY = "sfm_range_spread"
"""Training split: :class:`~seathru_nerfstudio.data.range_diversity.RangeSpread` of the SfM points, world units."""
SFM_OBSERVATIONS_KEY = "sfm_observations"
"""Training split: :class:`~seathru_nerfstudio.data.sfm_observations.SfmObservations`, world units."""
SCALE_KEY = "dataparser_scale"
"""Scene units per world unit (a float)."""
EXTENT_KEY = "frustum_extent"
"""The largest ``|x|∞`` (scene units) of the split's view frustums cut at the far bound
(:func:`~seathru_nerfstudio.data.nerfstudio_data.frustum_extent`), where the model's scene
contraction starts."""
VERTICAL_KEY = "scene_vertical"
"""The scene frame's unit vertical from the split's cameras (:func:`~seathru_nerfstudio.vertical.scene_vertical`), three floats."""
