"""mpib_validate: layered (MPI) bokeh, validated against physically based thin-lens renders.

Units used throughout the package:
- image coordinates (x, y) in pixels, measured from the image centre, y pointing down;
- disparity d = 1/Z in 1/scene-unit (Z is depth along the optical axis);
- blur parameter A in pixels per unit of disparity, so a point at disparity d is
  blurred into a disk of radius A |d - d_f| pixels;
- colours are linear radiance (HDR allowed), alpha is straight unless a name says
  "premultiplied".
"""

__version__ = "0.1.0"
