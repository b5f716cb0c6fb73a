"""GeoPose: population-trained C-arm pose estimation for CTA-to-DSA registration.

The library behind the 3D Slicer extension; it imports without Slicer.
"""

__version__ = "0.1.0"
