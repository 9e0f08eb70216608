"""LPIPS (Zhang et al. 2018), AlexNet, version 0.1: the definition of the ``lpips`` package,
in plain PyTorch.

Why not call the package: it builds AlexNet through torchvision, and PyPI's torchvision does
not import beside the CPU build of torch this project pins. The metric itself is small:
scale the [-1, 1] input per channel, take AlexNet's five ReLU outputs, normalise each
feature vector to unit length, square the difference, weight the channels with a 1×1
convolution (the learned "lin" layers), average over the image and sum over layers.

Two weight files are needed, and neither is invented here:
- the AlexNet backbone, torchvision's ``alexnet-owt-7be5be79.pth`` state dict (keys
  ``features.N.weight``), from ``--lpips-weights PATH`` or torch hub's cache, where it is
  downloaded once from torchvision's published URL (:func:`fetch_backbone`: torch hub's own
  downloader, which checks the SHA-256 prefix the file name carries);
- the lin layers, ``lpips/weights/v0.1/alex.pth`` as shipped inside the ``lpips`` package
  (installed without dependencies: only that file is read), or ``--lpips-linear PATH``.
When one is missing (offline, say), :func:`load_lpips` raises :class:`LpipsUnavailable` with
the reason, and the callers report LPIPS as unavailable rather than a number.
"""

from __future__ import annotations

import importlib.util
import re
import socket
import urllib.parse
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

BACKBONE_FILE = "alexnet-owt-7be5be79.pth"  # torchvision's name for the ImageNet AlexNet
BACKBONE_URL = "https://download.pytorch.org/models/" + BACKBONE_FILE  # where torchvision publishes it
DOWNLOAD_TIMEOUT_S = 60.0  # per network operation: a dropped connection fails instead of hanging
# The lpips package's ScalingLayer: ImageNet statistics expressed for inputs in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# AlexNet's conv layers as (index in torchvision's ``features``, in, out, kernel, stride, padding);
# max-pools sit at indices 2, 5 and 12. LPIPS reads the ReLU after each conv.
_CONVS = ((0, 3, 64, 11, 4, 2), (3, 64, 192, 5, 1, 2), (6, 192, 384, 3, 1, 1),
          (8, 384, 256, 3, 1, 1), (10, 256, 256, 3, 1, 1))
CHANNELS = tuple(c[2] for c in _CONVS)


class LpipsUnavailable(Exception):
    """LPIPS cannot be computed here; the message says why and how to enable it."""


class AlexNetFeatures(nn.Module):
    """AlexNet's convolutional trunk; ``forward`` returns the five ReLU outputs LPIPS uses.
    Parameter names match torchvision's ``alexnet().features`` so its state dict loads."""

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.ModuleDict({
            str(index): nn.Conv2d(cin, cout, kernel, stride=stride, padding=padding)
            for index, cin, cout, kernel, stride, padding in _CONVS
        })

    def forward(self, x: Tensor) -> list[Tensor]:
        taps = []
        for index, *_ in _CONVS:
            if index in (3, 6):  # max-pool before conv 2 and conv 3
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(self.features[str(index)](x))
            taps.append(x)
        return taps


class Lpips(nn.Module):
    """``forward(a, b)``: images ``[N, 3, H, W]`` in [0, 1] → distance ``[N]`` (0: identical).

    Example:
        >>> metric = load_lpips(backbone_path, linear_path)  # doctest: +SKIP
        >>> metric(torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64)).shape  # doctest: +SKIP
        torch.Size([1])
    """

    def __init__(self) -> None:
        super().__init__()
        self.backbone = AlexNetFeatures()
        self.linear = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in CHANNELS)
        self.register_buffer("shift", torch.tensor(SHIFT)[None, :, None, None])
        self.register_buffer("scale", torch.tensor(SCALE)[None, :, None, None])

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        features_a = self.backbone((a * 2 - 1 - self.shift) / self.scale)
        features_b = self.backbone((b * 2 - 1 - self.shift) / self.scale)
        total = a.new_zeros(a.shape[0])
        for fa, fb, linear in zip(features_a, features_b, self.linear):
            difference = (_unit(fa) - _unit(fb)) ** 2
            total = total + linear(difference).mean(dim=(1, 2, 3))
        return total


def _unit(features: Tensor, eps: float = 1e-10) -> Tensor:
    """Each pixel's feature vector divided by its length (the package's ``normalize_tensor``)."""
    return features / (features.pow(2).sum(dim=1, keepdim=True).sqrt() + eps)


def default_backbone_path() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / BACKBONE_FILE


def default_linear_path() -> Path | None:
    """The v0.1 AlexNet lin weights shipped in the ``lpips`` package, found without importing it
    (its import needs torchvision)."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0]) / "weights" / "v0.1" / "alex.pth"


_fetch_failure: str | None = None  # why this process's download failed: not tried again per eval


def fetch_backbone(url: str | None = None, destination: Path | None = None, progress: bool = True) -> Path:
    """The backbone at ``destination`` (default: torch hub's cache), downloaded from ``url``
    (default: torchvision's) if it is not there yet. The file must hash to the SHA-256 prefix its name carries
    (``NAME-<hex>.pth``, torchvision's convention): a file that does not is refused and nothing
    is kept. Raises :class:`LpipsUnavailable` with the reason (no network, refused hash)."""
    url = url or BACKBONE_URL
    destination = Path(destination) if destination is not None else default_backbone_path()
    if destination.is_file():
        return destination
    prefix = re.search(r"-([0-9a-f]{6,})\.[^.]+$", destination.name)
    if prefix is None:
        raise ValueError(f"{destination.name}: no SHA-256 prefix in the file name to check the download against")
    destination.parent.mkdir(parents=True, exist_ok=True)
    # Named without its scheme: the reason ends up in self-contained HTML reports, which link nowhere.
    parts = urllib.parse.urlsplit(url)
    source = f"{Path(parts.path).name} from {parts.netloc or parts.path}"
    previous = socket.getdefaulttimeout()
    socket.setdefaulttimeout(DOWNLOAD_TIMEOUT_S)
    try:  # torch hub's downloader: a temporary file beside the destination, renamed once checked
        torch.hub.download_url_to_file(url, str(destination), hash_prefix=prefix.group(1), progress=progress)
    except RuntimeError as exc:
        raise LpipsUnavailable(f"{source}: refused, its SHA-256 does not start with {prefix.group(1)} as "
                               f"{destination.name} says ({exc}); nothing was kept") from None
    except OSError as exc:  # URLError, timeouts, a full disk
        raise LpipsUnavailable(f"could not download {source} into {destination} ({getattr(exc, 'reason', exc)}); "
                               f"with no network, give --lpips-weights PATH to {BACKBONE_FILE}") from None
    finally:
        socket.setdefaulttimeout(previous)
    return destination


def _backbone_in_cache() -> Path:
    """torch hub's cached backbone, downloaded on first use (one try per process)."""
    global _fetch_failure
    if _fetch_failure is None:
        try:
            return fetch_backbone()
        except LpipsUnavailable as exc:
            _fetch_failure = str(exc)
    raise LpipsUnavailable(_fetch_failure)


def load_lpips(backbone: Path | None = None, linear: Path | None = None, device: torch.device | str = "cpu") -> Lpips:
    """The metric with its weights, or :class:`LpipsUnavailable` saying which file is missing.
    Without ``backbone``, torch hub's cached one, downloaded there on first use."""
    linear = Path(linear) if linear is not None else default_linear_path()
    if linear is None or not linear.is_file():  # checked first: no download for a metric that cannot run
        raise LpipsUnavailable(
            f"the LPIPS v0.1 linear-layer weights are not on this machine ({linear or 'no lpips package'}); "
            f"install them with 'pip install --no-deps lpips' or pass --lpips-linear PATH")
    backbone = Path(backbone) if backbone is not None else _backbone_in_cache()
    if not backbone.is_file():
        raise LpipsUnavailable(f"no AlexNet weights at {backbone} (give --lpips-weights PATH to {BACKBONE_FILE})")
    metric = Lpips()
    try:
        backbone_state = torch.load(backbone, map_location="cpu", weights_only=True)
        linear_state = torch.load(linear, map_location="cpu", weights_only=True)
        metric.backbone.features.load_state_dict(
            {key.removeprefix("features."): value for key, value in backbone_state.items() if key.startswith("features.")})
        # The package stores lin layer k as "link.model.1.weight" (after a dropout) or "link.model.0.weight".
        for k, layer in enumerate(metric.linear):
            weight = [value for key, value in linear_state.items() if key.startswith(f"lin{k}.") and key.endswith(".weight")]
            if len(weight) != 1:
                raise KeyError(f"lin{k} weight")
            layer.weight.data.copy_(weight[0])
    except (RuntimeError, KeyError, OSError, ValueError) as exc:
        raise LpipsUnavailable(f"LPIPS weights could not be loaded from {backbone} and {linear}: {exc}") from None
    return metric.eval().to(device)


@torch.no_grad()
def lpips_distance(metric: Lpips, a, b) -> float:
    """LPIPS between two ``[H, W, 3]`` images in [0, 1] (numpy arrays or tensors)."""
    device = metric.shift.device
    to_batch = lambda image: torch.as_tensor(image, dtype=torch.float32, device=device).permute(2, 0, 1)[None]
    return float(metric(to_batch(a), to_batch(b))[0])
