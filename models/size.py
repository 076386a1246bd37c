"""The networks' size multiple (no dependencies: the runtime, the data checks and the training
layers all read it from here).

The U-Net backbone (:mod:`polrig.models.layers`) has three stride-2 stages, so input height and width
must be multiples of ``2**3``; the runtime pads to it, training and evaluation sets are made
with sides that are multiples of it (``polrig sim dataset --size``).
"""

#: Height and width of network inputs must be multiples of this (three stride-2 stages).
SIZE_MULTIPLE = 8
