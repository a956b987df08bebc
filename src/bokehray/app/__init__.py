"""The applications on the library: the command line (``cli``, ``render_job``, ``batch``, ``demo``), the refocus
page (``view``) and the benchmark (``bench``)."""
