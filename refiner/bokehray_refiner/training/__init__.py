"""How the shipped networks are made: the training recipes, not needed at run time.

* ``data``: training pairs (``bokehray synth`` folders, their maps corrupted as real maps are: ``corrupt_disparity``)
  and the bank of pairs the residual network trains on (``PairBank``);
* ``residual``: the residual network's recipe (``bokehray train-refiner``), ``weights/refiner.safetensors``;
* ``edges``: the edge network's recipe, ``python -m bokehray_refiner.training.edges``, which rebuilds
  ``weights/edges.safetensors``.

See docs/refiner.md, "How the weights are made".
"""
