"""DriveTrack Release: long-range point-track annotations from driving logs, as versioned releases."""
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("drivetrack")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"
