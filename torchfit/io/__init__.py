"""Input and output: camera files, images and masks, datasets, meshes and exports (trimesh
lives here)."""

from torchfit.io.bvh import Motion, read_bvh, write_bvh
from torchfit.io.camera import (
    camera_from_dict,
    camera_to_dict,
    load_camera,
    load_stereo_cameras,
    save_camera,
    save_stereo_cameras,
)
from torchfit.io.dataset import StereoInfo, Subject, load_dataset, load_subject, validate_subject
from torchfit.io.export import export_mesh, export_urdf, write_json
from torchfit.io.images import (
    IMAGE_SUFFIXES,
    list_images,
    load_frames,
    read_image,
    read_mask,
    write_mask,
)
from torchfit.io.meshes import load_mesh_arrays, save_mesh

__all__ = [
    "load_camera",
    "save_camera",
    "camera_from_dict",
    "camera_to_dict",
    "load_stereo_cameras",
    "save_stereo_cameras",
    "IMAGE_SUFFIXES",
    "list_images",
    "read_image",
    "read_mask",
    "write_mask",
    "load_frames",
    "Subject",
    "StereoInfo",
    "load_dataset",
    "load_subject",
    "validate_subject",
    "load_mesh_arrays",
    "save_mesh",
    "export_urdf",
    "export_mesh",
    "write_json",
    "Motion",
    "read_bvh",
    "write_bvh",
]
