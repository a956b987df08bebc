"""The photo end: files and depth maps as people have them, read into scene-linear pixels and disparity.

``read`` (images, disparity maps: formats, decoding, checks), ``embedded`` (EXIF orientation, ICC profiles),
``depth`` (relative, reversed, integer and metric maps: the one depth reader), ``highlights`` (clipped lights),
``subject`` (the default blur amount and focus), ``depth_model`` (a monocular estimator from a local checkpoint).
"""
