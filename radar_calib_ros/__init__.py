"""radar_calib_ros: target-less geo-referenced extrinsic calibration of roadside radars."""
from radar_calib_ros.config import CalibConfig
from radar_calib_ros.errors import (
    BagReadError, CalibrationError, ConfigError, DecodeError, InsufficientDataError,
    NotConvergedError, ResultFileError)

__all__ = ['BagReadError', 'CalibConfig', 'CalibrationError', 'ConfigError', 'DecodeError',
           'InsufficientDataError', 'NotConvergedError', 'ResultFileError']
__version__ = '0.1.0'
