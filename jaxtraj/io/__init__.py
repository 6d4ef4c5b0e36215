"""Host-side readers and writers of file formats (the edge of the library)."""

from .bvh import Y_UP_TO_Z_UP as Y_UP_TO_Z_UP
from .bvh import BVHMotion as BVHMotion
from .bvh import load_bvh as load_bvh
from .bvh import parse_bvh as parse_bvh
from .euroc import EurocRecording as EurocRecording
from .euroc import ground_truth_as_robot as ground_truth_as_robot
from .euroc import read_euroc as read_euroc
from .euroc import read_euroc_csv as read_euroc_csv
