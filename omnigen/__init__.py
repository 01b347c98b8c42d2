"""omnigen: training data for calibration-free monocular 3D object detection in cities.

The core package: the contract (conventions), geometry, the UrbanOmniView record and dataset
folders, exports and the command line. scenes/, rigs/, converters/ and detector/ build on it.
"""

__version__ = "0.1.0"
