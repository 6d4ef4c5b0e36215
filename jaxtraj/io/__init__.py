"""Host-side readers and writers of file formats (the edge of the library).

The recording folder and its files: :mod:`.recording`, :mod:`.csv_formats`,
:mod:`.json_formats` (both re-exported by :mod:`.formats`), :mod:`.tables`;
plain records passed between files and the library: :mod:`.records`; motion capture
(:mod:`.bvh`) and EuRoC (:mod:`.euroc`) readers; plots (:mod:`.plots`).
"""

from .bvh import Y_UP_TO_Z_UP as Y_UP_TO_Z_UP
from .bvh import BVHMotion as BVHMotion
from .bvh import load_bvh as load_bvh
from .bvh import parse_bvh as parse_bvh
from .corners import read_corners as read_corners
from .corners import write_corners as write_corners
from .csv_formats import ImuSamples as ImuSamples
from .csv_formats import kuka_to_pose as kuka_to_pose
from .csv_formats import pose_to_kuka as pose_to_kuka
from .csv_formats import read_detections as read_detections
from .csv_formats import read_imu as read_imu
from .csv_formats import read_poses as read_poses
from .csv_formats import read_robot as read_robot
from .csv_formats import read_tum as read_tum
from .csv_formats import write_detections as write_detections
from .csv_formats import write_imu as write_imu
from .csv_formats import write_poses as write_poses
from .csv_formats import write_robot as write_robot
from .csv_formats import write_tum as write_tum
from .euroc import EurocRecording as EurocRecording
from .euroc import ground_truth_as_robot as ground_truth_as_robot
from .euroc import read_euroc as read_euroc
from .euroc import read_euroc_csv as read_euroc_csv
from .json_formats import RecordingMeta as RecordingMeta
from .json_formats import read_camera as read_camera
from .json_formats import read_object as read_object
from .json_formats import write_camera as write_camera
from .json_formats import write_object as write_object
from .recording import Recording as Recording
from .recording import Truth as Truth
from .recording import read_recording as read_recording
from .recording import read_truth as read_truth
from .recording import write_recording as write_recording
from .records import CameraCalibration as CameraCalibration
from .records import Detections as Detections
from .records import ObjectModel as ObjectModel
from .records import PoseStream as PoseStream
from .robot_poses import RobotPoses as RobotPoses
from .robot_poses import read_robot_poses as read_robot_poses
from .tables import RecordingError as RecordingError
from .tables import atomic_folder as atomic_folder
from .tables import atomic_write_text as atomic_write_text
