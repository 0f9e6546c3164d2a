"""Types of vkdr's compiled module (bindings/python/src). Arrays are NumPy arrays; an
argument typed `ArrayLike` also takes lists, tuples, integers where numbers are meant, and
CPU tensors (detached). A pose is 6 numbers (translation in metres, axis-angle in radians,
object to camera); `K` a 3 x 3 pinhole matrix or (fx, fy, cx, cy) in pixels; `size` is
(width, height); images are (H, W) arrays; a mask is object where above 0."""

from os import PathLike
from typing import Any, Callable, Literal, Sequence

import numpy as np
import numpy.typing as npt

ArrayLike = npt.ArrayLike
Path = str | PathLike[str]
Progress = Callable[[int, int], object]
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

__version__: str
UNKNOWN: float

class Device:
    """A Vulkan device: `Device()` picks the best (a discrete GPU first; `VKDR_DEVICE` or
    `name`, an index or part of a name, chooses another). A Device made before a fork
    refuses to work in the child (make one there)."""

    def __init__(self, name: str | None = None, validation: bool = False) -> None: ...
    @property
    def name(self) -> str: ...
    @property
    def kind(self) -> str: ...
    @property
    def api_version(self) -> str: ...
    @property
    def driver(self) -> str: ...
    @property
    def limits(self) -> dict[str, Any]: ...
    @property
    def engine_ms(self) -> float:
        """The last call's time in the engine, milliseconds."""
    def rasterize(
        self,
        vertices: ArrayLike,
        faces: ArrayLike,
        K: ArrayLike,
        size: ArrayLike,
        poses: ArrayLike,
    ) -> tuple[npt.NDArray[np.uint32], F32, F32]:
        """(ids, bary, depth) at each pixel centre: triangle id + 1 (0 on background), the
        barycentric weights of corners 0 and 1, the camera-space depth (0 on background);
        (H, W, ...) for one pose (6,), (N, H, W, ...) for several (N, 6)."""
    def visibility(
        self,
        vertices: ArrayLike,
        faces: ArrayLike,
        K: ArrayLike,
        size: ArrayLike,
        poses: ArrayLike,
    ) -> npt.NDArray[np.uint32]:
        """`rasterize`'s ids alone (triangle id + 1, 0 on background), (H, W) or (N, H, W):
        a quarter of the memory read back."""
    def loss_and_grad(
        self,
        vertices: ArrayLike,
        faces: ArrayLike,
        K: ArrayLike,
        size: ArrayLike,
        pose: ArrayLike,
        mask: ArrayLike,
        loss: Literal["mse", "iou", "distance"] = "mse",
        depth: ArrayLike | None = None,
        shading: ArrayLike | None = None,
        ignore: ArrayLike | None = None,
        depth_sigma: float | None = None,
        depth_weight: float | None = None,
        occlusion: float | None = None,
        light: Sequence[float] | None = None,
        ambient: float | None = None,
    ) -> tuple[float, F64, F64]:
        """(loss, dL/dvertices (V, 3), dL/dpose (6,)) of the mesh's rendering against
        `mask`, with vkdr's exact gradients."""
    def register(
        self,
        space: ShapeSpace,
        mask: ArrayLike,
        K: ArrayLike,
        size: ArrayLike,
        pose: ArrayLike,
        *,
        depth: ArrayLike | None = None,
        shading: ArrayLike | None = None,
        ignore: ArrayLike | None = None,
        views: list[dict[str, Any]] | None = None,
        progress: Progress | None = None,
        **options: Any,
    ) -> Registration:
        """Fits `space`'s code (and with `optimize_pose=True` the pose) to the observation;
        the options are `vkdr register`'s flags (docs/python.md)."""
    def register_batch(
        self,
        space: ShapeSpace,
        masks: ArrayLike,
        K: ArrayLike,
        size: ArrayLike,
        poses: ArrayLike,
        *,
        depths: ArrayLike | None = None,
        progress: Progress | None = None,
        **options: Any,
    ) -> list[Registration]:
        """`register` of each of masks (N, H, W) from poses (N, 6), in one call."""

class ShapeSpace:
    """A category's latent shape space (canonical mesh, PCA of CPD deformations)."""

    @staticmethod
    def build(
        vertices: ArrayLike,
        faces: ArrayLike,
        instances: Sequence[ArrayLike],
        dims: int = 5,
        category: str = "object",
        names: Sequence[str] | None = None,
        beta: float | None = None,
        lam: float | None = None,
        w: float | None = None,
        device: Device | None = None,
        progress: Progress | None = None,
        up: ArrayLike | None = None,
    ) -> ShapeSpace: ...
    @staticmethod
    def load(path: Path) -> ShapeSpace:
        """A space from its .npz file (the .npz.json beside it for older files)."""
    def save(self, path: Path) -> None:
        """Writes the .npz (enough to load) and the .npz.json (its description)."""
    def to_bytes(self) -> bytes: ...
    @staticmethod
    def from_bytes(data: bytes) -> ShapeSpace: ...
    def vertices(self, code: ArrayLike) -> F64:
        """The canonical deformed by `code` (dims,): (V, 3)."""
    def code_in_deviations(self, code: ArrayLike) -> F64: ...
    @property
    def dims(self) -> int: ...
    @property
    def category(self) -> str: ...
    @property
    def canonical(self) -> F32: ...
    @property
    def faces(self) -> npt.NDArray[np.uint32]: ...
    @property
    def training_codes(self) -> F64: ...
    @property
    def training_names(self) -> list[str]: ...

class Registration:
    """What a registration found (pickles with its space)."""

    @property
    def code(self) -> F64: ...
    @property
    def code_sd(self) -> F64: ...
    @property
    def pose(self) -> F64: ...
    @property
    def vertices(self) -> F64: ...
    @property
    def faces(self) -> npt.NDArray[np.uint32]: ...
    @property
    def losses(self) -> F64: ...
    @property
    def stages(self) -> list[tuple[str, int]]:
        """(name, count) of each stage `losses` holds, in order; the counts add up to
        len(losses)."""
    @property
    def loss(self) -> float: ...
    @property
    def iterations(self) -> int:
        """The iterations whose losses are kept: the stages' counts, len(losses)."""
    @property
    def evaluations(self) -> int:
        """Every evaluation made, the turns' checks and a replaced joint fit included
        (what `milliseconds` paid for)."""
    @property
    def milliseconds(self) -> float: ...
    @property
    def scale(self) -> float: ...

def cpd(
    source: ArrayLike,
    target: ArrayLike,
    beta: float | None = None,
    lam: float | None = None,
    w: float | None = None,
    max_iterations: int | None = None,
    tolerance: float | None = None,
    device: Device | None = None,
    progress: Progress | None = None,
) -> tuple[F64, F64, dict[str, Any]]:
    """Non-rigid CPD of source (M, 3) onto target (N, 3): (deformed, W, log)."""

def load_mesh(path: Path) -> tuple[F32, npt.NDArray[np.uint32]]:
    """An OBJ's vertices (V, 3) and triangles (F, 3)."""

def default_device() -> Device:
    """The device of calls given none, made on first use."""
