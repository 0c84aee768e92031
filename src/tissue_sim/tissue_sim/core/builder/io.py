"""Loading label volumes: NIfTI, a folder of per-slice PNGs + spacing.yaml, or .npz.

Every loader returns a :class:`LabelVolume`: integer labels ``(I, J, K)`` (``K`` = slice axis, along
the body's long axis) and the 4x4 affine voxel index -> RAS+ millimetres. Bad input raises
``tissue_sim.errors.UserError`` naming the file and the problem.
"""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np

from tissue_sim.errors import UserError


@dataclasses.dataclass(frozen=True)
class LabelVolume:
    labels: np.ndarray          # (I, J, K) integer, 0 = background
    affine: np.ndarray          # (4, 4) voxel (i, j, k, 1) -> RAS+ mm
    source: str = '<array>'

    @property
    def pixel_mm(self) -> tuple:
        """In-plane voxel size (along i, along j) and slice spacing, in mm."""
        a = self.affine[:3, :3]
        return tuple(float(np.linalg.norm(a[:, c])) for c in range(3))


def _check_volume(labels, affine, source) -> LabelVolume:
    labels = np.asarray(labels)
    affine = np.asarray(affine, dtype=np.float64)
    if labels.ndim == 4 and labels.shape[3] == 1:
        labels = labels[..., 0]
    if labels.ndim != 3:
        raise UserError(f'{source}: label volume must be 3-D (I, J, K), got shape {labels.shape}')
    if min(labels.shape) < 1 or labels.shape[2] < 2:
        raise UserError(f'{source}: label volume needs at least 2 slices, got shape {labels.shape}')
    if labels.dtype.kind == 'f':
        if not np.all(np.isfinite(labels)) or np.any(labels != np.round(labels)):
            raise UserError(f'{source}: labels must be integers (found non-integer values)')
        labels = labels.astype(np.int32)
    elif labels.dtype.kind not in 'iub':
        raise UserError(f'{source}: labels must be integers, got dtype {labels.dtype}')
    if labels.dtype.kind == 'b':
        labels = labels.astype(np.int32)
    if labels.min() < 0:
        raise UserError(f'{source}: negative label {int(labels.min())}')
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)):
        raise UserError(f'{source}: affine must be a finite 4x4 matrix')
    a = affine[:3, :3]
    sizes = np.linalg.norm(a, axis=0)
    if np.any(sizes <= 1e-9) or abs(np.linalg.det(a)) < 1e-12:
        raise UserError(f'{source}: wrong spacing: voxel sizes {sizes.round(4).tolist()} mm (must be > 0, non-degenerate affine)')
    # slices must be the (i, j) planes, perpendicular to the long (S) axis
    for c, nm in ((0, 'i'), (1, 'j')):
        if abs(a[2, c]) > 1e-3 * sizes[c]:
            raise UserError(f'{source}: the {nm} voxel axis has a superior component ({a[2, c]:.4g} mm): '
                            'slices must be the (i, j) planes perpendicular to the body long axis (reslice the volume)')
    if abs(a[2, 2]) < 0.5 * sizes[2]:
        raise UserError(f'{source}: the slice axis (k) does not run along the body long axis (superior-inferior)')
    # Fortran order: every (i, j) slice is one contiguous block (nibabel's native order)
    return LabelVolume(np.asfortranarray(labels), affine, str(source))


def _size_text(n: int) -> str:
    for unit, f in (('GiB', 2 ** 30), ('MiB', 2 ** 20), ('KiB', 2 ** 10)):
        if n >= f:
            return f'{n / f:.1f} {unit}'
    return f'{n} bytes'


def _gzip_holds_at_least(path: Path, need: int) -> int:
    """Bytes of decompressed data in a gzip file, counted by streaming (no large allocation) and
    stopping as soon as ``need`` bytes are seen; a shorter count means the file is truncated."""
    import gzip
    got = 0
    with gzip.open(path, 'rb') as f:
        while got < need:
            chunk = f.read(min(1 << 22, need - got))
            if not chunk:
                break
            got += len(chunk)
    return got


def _check_nifti_header(path: Path) -> float:
    """Check the raw NIfTI header before any voxel data is read: positive finite voxel sizes when
    no sform/qform gives the geometry (nibabel silently turns a zero pixdim into 1 mm), and a data
    size the file can hold (a corrupt header would otherwise allocate what it declares).
    Returns the factor to millimetres of the header's spatial unit."""
    import gzip
    import io as _io

    import nibabel as nib
    gz = path.name.lower().endswith('.gz')
    try:
        with (gzip.open(path, 'rb') if gz else open(path, 'rb')) as f:
            raw = f.read(540)
    except (OSError, EOFError) as e:
        raise UserError(f'{path}: unreadable NIfTI file ({type(e).__name__}: {e})') from None
    if len(raw) < 348:
        raise UserError(f'{path}: unreadable NIfTI file (only {len(raw)} bytes, a NIfTI header has 348)')
    sizeof = {int(np.frombuffer(raw[:4], e)[0]): e for e in ('<i4', '>i4')}
    cls = nib.Nifti1Header if 348 in sizeof else nib.Nifti2Header if 540 in sizeof else None
    if cls is None:
        raise UserError(f'{path}: unreadable NIfTI file (header size field is not 348 or 540)')
    try:
        hdr = cls.from_fileobj(_io.BytesIO(raw), check=False)
        shape = tuple(int(n) for n in hdr.get_data_shape())
        itemsize = int(hdr['bitpix']) // 8
        offset = int(hdr['vox_offset'])
    except Exception as e:  # nibabel raises many kinds
        raise UserError(f'{path}: unreadable NIfTI header ({type(e).__name__}: {e})') from None
    pix = np.asarray(hdr['pixdim'][1:4], dtype=np.float64)
    if int(hdr['sform_code']) == 0 and not (np.all(np.isfinite(pix)) and np.all(pix > 0)):
        raise UserError(f'{path}: wrong spacing: voxel sizes pixdim[1:4] = {pix.tolist()} mm must be positive numbers '
                        '(the file has no sform that would give the geometry otherwise)')
    if any(n < 0 for n in shape) or itemsize <= 0:
        raise UserError(f'{path}: unreadable NIfTI header (shape {shape}, {8 * itemsize} bits per voxel)')
    need = offset + int(np.prod(shape, dtype=object)) * itemsize
    if gz:
        # the gzip trailer holds the data size modulo 2^32 (of the last member): trust it only when it matches
        try:
            with open(path, 'rb') as f:
                f.seek(-4, 2)
                isize = int.from_bytes(f.read(4), 'little')
        except OSError:
            isize = -1
        try:
            have = need if (need < 2 ** 32 and isize == need) else _gzip_holds_at_least(path, need)
        except (OSError, EOFError, gzip.BadGzipFile) as e:
            raise UserError(f'{path}: unreadable NIfTI file ({type(e).__name__}: {e})') from None
    else:
        have = path.stat().st_size
    if have < need:
        raise UserError(f'{path}: truncated NIfTI file: the header declares {shape} voxels of {itemsize} bytes '
                        f'({_size_text(need)} with the header) but the file holds {_size_text(have)}'
                        + (' uncompressed' if gz else ''))
    units = int(hdr['xyzt_units']) & 7
    return {1: 1000.0, 3: 0.001}.get(units, 1.0)     # metre, micron; mm or unknown: mm


def _load_nifti(path: Path) -> LabelVolume:
    import nibabel as nib
    to_mm = _check_nifti_header(path)
    try:
        img = nib.load(str(path))
        data = np.asanyarray(img.dataobj)
    except Exception as e:  # nibabel raises many kinds
        raise UserError(f'{path}: unreadable NIfTI file ({type(e).__name__}: {e})') from None
    affine = np.array(img.affine, dtype=np.float64)
    affine[:3] *= to_mm
    return _check_volume(data, affine, path)


def _load_npz(path: Path) -> LabelVolume:
    try:
        with np.load(path, allow_pickle=False) as z:
            if 'labels' not in z.files or 'affine' not in z.files:
                raise UserError(f'{path}: .npz label volume needs arrays "labels" and "affine" (has {z.files})')
            return _check_volume(z['labels'], z['affine'], path)
    except UserError:
        raise
    except Exception as e:
        raise UserError(f'{path}: unreadable .npz file ({type(e).__name__}: {e})') from None


def _load_png_folder(path: Path) -> LabelVolume:
    import imageio.v3 as iio
    import yaml
    sp = path / 'spacing.yaml'
    if not sp.is_file():
        raise UserError(f'{path}: a PNG slice folder needs spacing.yaml (pixel_mm, slice_mm, origin_mm)')
    try:
        spec = yaml.safe_load(sp.read_text()) or {}
    except yaml.YAMLError as e:
        raise UserError(f'{sp}: not valid YAML ({e})') from None
    try:
        dx, dy = (float(v) for v in spec['pixel_mm'])
        dz = float(spec['slice_mm'])
        origin = [float(v) for v in spec.get('origin_mm', [0.0, 0.0, 0.0])]
    except (KeyError, TypeError, ValueError) as e:
        raise UserError(f'{sp}: wrong spacing: needs pixel_mm: [dx, dy], slice_mm: dz, origin_mm: [x, y, z] ({e})') from None
    if not all(np.isfinite([dx, dy, dz])) or min(dx, dy, dz) <= 0:
        raise UserError(f'{sp}: wrong spacing: pixel_mm {[dx, dy]}, slice_mm {dz} must be positive numbers')
    if len(origin) != 3 or not all(np.isfinite(origin)):
        raise UserError(f'{sp}: origin_mm must be 3 finite numbers [x, y, z], got {spec.get("origin_mm")!r}')
    if not isinstance(spec.get('first_slice_superior', False), bool):
        raise UserError(f'{sp}: first_slice_superior must be true or false, got {spec["first_slice_superior"]!r}')
    files = sorted((f for f in path.iterdir() if re.fullmatch(r'slice_\d+\.png', f.name)),
                   key=lambda f: int(f.stem.split('_')[1]))
    if len(files) < 2:
        raise UserError(f'{path}: needs at least 2 files slice_0000.png, slice_0001.png, ... (found {len(files)})')
    idx = [int(f.stem.split('_')[1]) for f in files]
    if idx != list(range(idx[0], idx[0] + len(idx))):
        raise UserError(f'{path}: slice files are not consecutively numbered (gap after slice {idx[0]})')
    imgs = []
    for f in files:
        try:
            im = iio.imread(f)
        except Exception as e:
            raise UserError(f'{f}: unreadable PNG ({type(e).__name__}: {e})') from None
        if im.ndim != 2:
            raise UserError(f'{f}: label PNG must be single-channel (8- or 16-bit grey), got shape {im.shape}')
        if imgs and im.shape != imgs[0].shape:
            raise UserError(f'{f}: inconsistent slices: size {im.shape} differs from {imgs[0].shape} of {files[0].name}')
        imgs.append(im)
    # PNG (row, col) -> volume (i = col, j = row, k = slice)
    labels = np.stack([im.T for im in imgs], axis=2).astype(np.int32)
    sz = -dz if spec.get('first_slice_superior', False) else dz
    # radiological display: columns run to the patient's left (R decreases), rows to posterior (A decreases)
    affine = np.array([[-dx, 0, 0, origin[0]], [0, -dy, 0, origin[1]], [0, 0, sz, origin[2]], [0, 0, 0, 1.0]])
    return _check_volume(labels, affine, path)


def load_labels(src, affine=None) -> LabelVolume:
    """Load a label volume from a path (.nii/.nii.gz, .npz, PNG folder), a LabelVolume, or an array + affine."""
    if isinstance(src, LabelVolume):
        return _check_volume(src.labels, src.affine, src.source)
    if isinstance(src, np.ndarray):
        if affine is None:
            raise UserError('a label array needs its affine (4x4, voxel -> RAS mm)')
        return _check_volume(src, affine, '<array>')
    path = Path(src)
    if not path.exists():
        raise UserError(f'{path}: no such file or folder')
    if path.is_dir():
        return _load_png_folder(path)
    name = path.name.lower()
    if name.endswith('.nii') or name.endswith('.nii.gz'):
        return _load_nifti(path)
    if name.endswith('.npz'):
        return _load_npz(path)
    raise UserError(f'{path}: unknown label file type (expected .nii, .nii.gz, .npz or a folder of slice PNGs)')


def voxel_to_model(affine: np.ndarray, ijk: np.ndarray) -> np.ndarray:
    """Voxel coordinates (..., 3) -> model frame metres: model = (A, -R, S) / 1000 (REP-103)."""
    ras = ijk @ affine[:3, :3].T + affine[:3, 3]
    return np.stack([ras[..., 1], -ras[..., 0], ras[..., 2]], axis=-1) / 1000.0


def model_from_ras_matrix() -> np.ndarray:
    """3x3 matrix M with model = M @ ras / 1000."""
    return np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
