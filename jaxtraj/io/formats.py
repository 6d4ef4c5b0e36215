"""Readers and writers of the individual files of a recording: an index.

The code lives in two modules; this one re-exports their public names so that
``from jaxtraj.io.formats import read_camera`` (and every other name) keeps working.

* :mod:`jaxtraj.io.csv_formats` - the CSV (and TUM text) files: ``imu.csv``,
  ``robot.csv`` (with the KUKA ``X,Y,Z,A,B,C`` conversions), pose CSV and TUM,
  ``detections.csv``, ``images.csv``, ``points.csv``.
* :mod:`jaxtraj.io.json_formats` - the JSON files: ``camera.json`` (or OpenCV's
  ``camera.yaml``), ``object.json``, ``recording.json``, and :func:`write_json`.

Every ``read_X`` stops bad input with one :class:`~jaxtraj.io.tables.RecordingError`
naming the file, the line (CSV, YAML, JSON syntax) or key (JSON) and the problem. Every
``write_X`` writes atomically and with enough digits that ``read_X(write_X(x)) == x``
exactly (floats use Python's shortest round-trip repr).

Files (see :mod:`jaxtraj.io.recording` for the folder):

* ``imu.csv``: ``t,wx,wy,wz,ax,ay,az`` (s, rad/s, m/s^2, IMU frame) or EuRoC's
  ``#timestamp [ns],w_RS_S_x [rad s^-1],...,a_RS_S_z [m s^-2]``.
* ``robot.csv``: flange poses ``T_w_f``, ``t,x,y,z,qw,qx,qy,qz`` (m, unit quaternion w
  first) or KUKA ``t,X,Y,Z,A,B,C`` (mm, degrees, R = Rz(A) Ry(B) Rx(C)).
* poses CSV ``t,x,y,z,qw,qx,qy,qz`` and TUM ``timestamp tx ty tz qx qy qz qw``.
* ``camera.json`` (or OpenCV's ``camera.yaml``), ``object.json``, ``recording.json``.
* ``detections.csv`` ``frame,t,id,u,v``; ``images.csv`` ``frame,t,file``;
  ``points.csv`` ``frame,t,id,x,y,z,ok``.
"""

from .csv_formats import DETECTION_COLUMNS as DETECTION_COLUMNS
from .csv_formats import EUROC_IMU_COLUMNS as EUROC_IMU_COLUMNS
from .csv_formats import IMU_COLUMNS as IMU_COLUMNS
from .csv_formats import KUKA_COLUMNS as KUKA_COLUMNS
from .csv_formats import POSE_COLUMNS as POSE_COLUMNS
from .csv_formats import ImuSamples as ImuSamples
from .csv_formats import ReconstructedPoints as ReconstructedPoints
from .csv_formats import kuka_to_pose as kuka_to_pose
from .csv_formats import pose_to_kuka as pose_to_kuka
from .csv_formats import read_detections as read_detections
from .csv_formats import read_image_index as read_image_index
from .csv_formats import read_imu as read_imu
from .csv_formats import read_points as read_points
from .csv_formats import read_poses as read_poses
from .csv_formats import read_robot as read_robot
from .csv_formats import read_tum as read_tum
from .csv_formats import write_detections as write_detections
from .csv_formats import write_image_index as write_image_index
from .csv_formats import write_imu as write_imu
from .csv_formats import write_points as write_points
from .csv_formats import write_poses as write_poses
from .csv_formats import write_robot as write_robot
from .csv_formats import write_tum as write_tum
from .json_formats import CAMERA_KEYS as CAMERA_KEYS
from .json_formats import META_KEYS as META_KEYS
from .json_formats import OBJECT_KEYS as OBJECT_KEYS
from .json_formats import ImuNoise as ImuNoise
from .json_formats import RecordingMeta as RecordingMeta
from .json_formats import RobotNoise as RobotNoise
from .json_formats import read_camera as read_camera
from .json_formats import read_meta as read_meta
from .json_formats import read_object as read_object
from .json_formats import write_camera as write_camera
from .json_formats import write_json as write_json
from .json_formats import write_meta as write_meta
from .json_formats import write_object as write_object

__all__ = [
    "ImuNoise",
    "ImuSamples",
    "ReconstructedPoints",
    "RecordingMeta",
    "RobotNoise",
    "kuka_to_pose",
    "pose_to_kuka",
    "read_camera",
    "read_detections",
    "read_image_index",
    "read_imu",
    "read_meta",
    "read_object",
    "read_points",
    "read_poses",
    "read_robot",
    "read_tum",
    "write_camera",
    "write_detections",
    "write_image_index",
    "write_imu",
    "write_json",
    "write_meta",
    "write_object",
    "write_points",
    "write_poses",
    "write_robot",
    "write_tum",
]
