"""The output end: images and disparity maps written atomically (``write``), and the one place for atomic writes
and the temporaries a killed writer leaves (``atomic``)."""
