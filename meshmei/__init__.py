"""meshmei: 3D maximally exciting inputs with RBF mesh deformation, a differentiable rasterizer and regularizers."""

from .errors import EncoderError, MEIError, MeshError, ReconstructionError, RenderError, TuningError
from .mesh import check_mesh, load_mesh, save_mesh
from .operators import (
    adjacency_list,
    cot_laplacian,
    cot_weights,
    cotmatrix,
    doublearea,
    edges,
    face_areas,
    face_normals,
    massmatrix,
    uniform_laplacian,
    vertex_normals,
)
from .regularizers import (
    arap_direction_loss,
    arap_loss,
    area_loss,
    best_fit_rotations,
    edge_loss,
    laplacian_loss,
)
from .shapes import bunny_path, initial_mesh, target_mesh
from .topology import MeshTopology, mesh_topology
from .render import Camera, Fragments, RenderSettings, camera_from_angles, rasterize, render
from .deform import RBFDeformer
from .metrics import SurfaceMetrics, surface_metrics
from .sampling import chamfer_distance, sample_points
from .reconstruct import ReconstructionResult, ReconstructionSettings, reconstruct
from .encoders import GaborComplexCell, GaborSimpleCell, CoreReadoutModel, ModelEncoder, encoder_from_model, load_demo_model, load_model
from .mei import MEIResult, MEISettings, load_run, optimize_mei, pixel_mei, save_run
from .tuning import light_sweep, pose_sweep

__version__ = "0.1.0"

__all__ = [
    "MeshError",
    "RenderError",
    "EncoderError",
    "MEIError",
    "ReconstructionError",
    "TuningError",
    "check_mesh",
    "load_mesh",
    "save_mesh",
    "adjacency_list",
    "cot_laplacian",
    "cot_weights",
    "cotmatrix",
    "doublearea",
    "edges",
    "face_areas",
    "face_normals",
    "massmatrix",
    "uniform_laplacian",
    "vertex_normals",
    "arap_direction_loss",
    "arap_loss",
    "area_loss",
    "best_fit_rotations",
    "edge_loss",
    "laplacian_loss",
    "bunny_path",
    "initial_mesh",
    "target_mesh",
    "MeshTopology",
    "mesh_topology",
    "Camera",
    "Fragments",
    "RenderSettings",
    "camera_from_angles",
    "rasterize",
    "render",
    "RBFDeformer",
    "chamfer_distance",
    "sample_points",
    "surface_metrics",
    "SurfaceMetrics",
    "reconstruct",
    "ReconstructionSettings",
    "ReconstructionResult",
    "GaborSimpleCell",
    "GaborComplexCell",
    "CoreReadoutModel",
    "load_demo_model",
    "ModelEncoder",
    "encoder_from_model",
    "load_model",
    "pixel_mei",
    "MEISettings",
    "MEIResult",
    "optimize_mei",
    "load_run",
    "save_run",
    "light_sweep",
    "pose_sweep",
]
