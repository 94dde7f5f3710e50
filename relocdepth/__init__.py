"""relocdepth: camera re-localization and monocular depth from unlabeled video."""

__version__ = "0.1.0"
