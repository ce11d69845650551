"""polarstripe: see through scattering media by controlling light before the image forms.

Implements Gupta, Narasimhan & Schechner, "On Controlling Light Transport in Poor Visibility
Environments" (CVPR 2008) as a set of ZeroMQ nodes. The repository root is this package:
``msgs/`` is :mod:`polarstripe.msgs`, ``sim/`` is :mod:`polarstripe.sim`, and so on.
"""

__version__ = "0.1.0"
