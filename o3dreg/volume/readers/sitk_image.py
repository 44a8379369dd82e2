"""Images SimpleITK reads (NIfTI, MetaImage, single DICOM files) as :class:`Volume`."""

from __future__ import annotations

import gzip
import logging
import os
import struct
import zlib
from typing import Any

import numpy as np

from ..volume import Volume

# SimpleITK is imported inside the readers (~0.5 s to import; `import o3dreg` loads this
# module).
__all__ = ["from_sitk", "read_sitk_file", "sitk_error"]

logger = logging.getLogger("o3dreg")


def sitk_error(exc: Exception) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for line in reversed(lines):
        if "ERROR" in line or "Error" in line or "error" in line:
            return line
    return lines[-1] if lines else type(exc).__name__


def from_sitk(image: Any, source: str) -> Volume:
    import SimpleITK as sitk

    dim = image.GetDimension()
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError(
            f"`path`: {source!r} holds {image.GetNumberOfComponentsPerPixel()} components per "
            "voxel; a volume needs one (a scalar image)"
        )
    if dim == 4:
        size = image.GetSize()
        if size[3] != 1:
            raise ValueError(
                f"`path`: {source!r} is a 4D image of size {size}; a volume needs 3 dimensions"
            )
        image = sitk.Extract(image, [*size[:3], 0], [0, 0, 0, 0])
        dim = 3
    if dim == 2:
        array = sitk.GetArrayFromImage(image)[np.newaxis]
        sx, sy = image.GetSpacing()
        thickness = _slice_thickness(image)
        ox, oy = image.GetOrigin()
        direction = np.eye(3)
        direction[:2, :2] = np.asarray(image.GetDirection(), dtype=np.float64).reshape(2, 2)
        return Volume(array, np.array([thickness, sy, sx]), np.array([ox, oy, 0.0]), direction)
    if dim != 3:
        raise ValueError(f"`path`: {source!r} is a {dim}D image; a volume needs 3 dimensions")
    array = sitk.GetArrayFromImage(image)
    spacing = np.asarray(image.GetSpacing(), dtype=np.float64)[::-1]
    if array.shape[0] == 1 and image.HasMetaDataKey("0018|0050"):
        spacing[0] = _slice_thickness(image)  # one DICOM slice: its thickness, as in a folder
    origin = np.asarray(image.GetOrigin(), dtype=np.float64)
    try:
        return Volume(array, spacing, origin, np.asarray(image.GetDirection(), dtype=np.float64))
    except ValueError as exc:  # a header with zero or NaN spacing, NaN origin, ...
        raise ValueError(f"`path`: {source!r} has an unusable geometry: {exc}") from exc


def _slice_thickness(image: Any) -> float:
    try:
        if image.HasMetaDataKey("0018|0050"):
            value = float(image.GetMetaData("0018|0050"))
            if np.isfinite(value) and value > 0:
                return value
    except (RuntimeError, ValueError):
        pass
    return 1.0


def read_sitk_file(path: str) -> Volume:
    import SimpleITK as sitk

    nifti = path.lower().endswith((".nii", ".nii.gz"))
    if path.lower().endswith((".mha", ".mhd")):
        _check_metaimage_compressed(path)
    head = _nifti_head(path) if nifti else b""  # the header, read once for the checks below
    nifti1 = _nifti1_header(head)
    if nifti:
        _check_nifti_complete(path, head)
        _check_nifti_spacing(path, head)
        _warn_if_qform_and_sform_differ(path, nifti1)
    try:
        image = sitk.ReadImage(path)
    except RuntimeError as exc:
        if nifti and nifti1 is None and _nifti_data_end(head, path) is not None:
            raise OSError(
                f"`path`: {path!r} is a NIfTI-2 file, which SimpleITK cannot read: save it as "
                "NIfTI-1 (for example nibabel.save(nibabel.Nifti1Image(image.dataobj, "
                "image.affine), 'scan.nii.gz'))"
            ) from exc
        raise OSError(f"`path`: could not read {path!r}: {sitk_error(exc)}") from exc
    if nifti:
        _space_voxels_by_the_sform(image, path, nifti1)
    volume = from_sitk(image, path)
    logger.info("read %s: %r", path, volume)
    return volume


#: Bytes per element of MetaImage's element types.
_MET_SIZES = {
    "MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4, "MET_UINT": 4,
    "MET_LONG": 4, "MET_ULONG": 4, "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8, "MET_FLOAT": 4,
    "MET_DOUBLE": 8,
}  # fmt: skip


def _check_metaimage_compressed(path: str) -> None:
    """``OSError`` when a MetaImage says ``CompressedData = True`` but its data does not
    inflate to the size its header needs: ITK prints "Uncompress failed" and returns whatever
    it has, garbage voxels (measured: values of +-22000 from a 0-6 image)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError:
        return  # SimpleITK says why
    fields: dict[str, str] = {}
    offset = 0
    for line in head.splitlines(keepends=True):
        offset += len(line)
        key, sep, value = line.decode("latin-1").partition("=")
        if not sep:
            return  # not a header we know: SimpleITK reports it
        fields[key.strip()] = value.strip()
        if key.strip() == "ElementDataFile":
            break
    else:
        return
    if fields.get("CompressedData", "").lower() != "true":
        return
    try:
        voxels = int(np.prod([int(d) for d in fields["DimSize"].split()], dtype=np.int64))
        channels = int(fields.get("ElementNumberOfChannels", "1"))
        expected = voxels * channels * _MET_SIZES[fields["ElementType"]]
    except (KeyError, ValueError):
        return
    data_file = fields["ElementDataFile"]
    if data_file == "LOCAL":
        source, start = path, offset
    elif " " not in data_file and not data_file.upper().startswith("LIST"):
        source, start = os.path.join(os.path.dirname(os.path.abspath(path)), data_file), 0
    else:
        return  # a list or pattern of files
    size, reason = _inflated_size(source, start, expected)
    if size != expected:
        raise OSError(
            f"`path`: {path!r} says its data is compressed (CompressedData = True) but it does "
            f"not inflate to the {expected} bytes its header needs ({reason}): the file is "
            "damaged, or its data is not compressed"
        )


def _inflated_size(path: str, start: int, limit: int) -> tuple[int, str]:
    """The size the zlib stream from byte ``start`` of ``path`` inflates to (counted in blocks,
    up to ``limit + 1``), and a word on it; ``-1`` and zlib's message if it is not one."""
    inflate = zlib.decompressobj()
    size = 0
    try:
        with open(path, "rb") as fh:
            fh.seek(start)
            while size <= limit and (block := fh.read(1 << 22)):
                size += len(inflate.decompress(block, limit + 1 - size))
                while inflate.unconsumed_tail and size <= limit:
                    size += len(inflate.decompress(inflate.unconsumed_tail, limit + 1 - size))
    except OSError:
        return limit, "unreadable: left to SimpleITK"  # it names the missing data file
    except zlib.error as exc:
        return -1, str(exc)
    return size, f"{size} bytes"


def _nifti_head(path: str) -> bytes:
    """The first 540 bytes of a (possibly gzipped) NIfTI file; what there is of them."""
    opener: Any = gzip.open if path.lower().endswith(".gz") else open
    try:
        with opener(path, "rb") as fh:
            return fh.read(540)
    except (EOFError, gzip.BadGzipFile, zlib.error) as exc:
        raise OSError(f"`path`: {path!r} is truncated or corrupt ({exc})") from exc


def _check_nifti_complete(path: str, head: bytes) -> None:
    """``OSError`` when a NIfTI file holds fewer voxel bytes than its header (``head``)
    promises.

    SimpleITK fills the missing part of a truncated ``.nii`` or ``.nii.gz`` with zeros.
    """
    expected = _nifti_data_end(head, path)
    if expected is None:
        return  # not a header we know: SimpleITK reports it
    if not path.lower().endswith(".gz"):
        size = os.path.getsize(path)
    else:
        size = 0
        try:
            with gzip.open(path, "rb") as fh:
                while block := fh.read(1 << 22):
                    size += len(block)
        except (EOFError, gzip.BadGzipFile, zlib.error) as exc:
            raise OSError(f"`path`: {path!r} is truncated or corrupt ({exc})") from exc
    if size < expected:
        raise OSError(
            f"`path`: {path!r} is truncated: {size} bytes where its header needs {expected}"
        )


def _check_nifti_spacing(path: str, head: bytes) -> None:
    """``ValueError`` when a NIfTI header's voxel sizes (``pixdim[1:4]``) are zero or not
    finite (SimpleITK reads such a size as 1 mm, which would place and scale the volume
    silently wrong), or negative."""
    for order in ("<", ">"):
        size = struct.unpack(order + "i", head[:4])[0] if len(head) >= 4 else 0
        if size == 348 and len(head) >= 348:
            pixdim = np.array(struct.unpack(order + "3f", head[80:92]), dtype=np.float64)
            break
        if size == 540 and len(head) >= 540:
            pixdim = np.array(struct.unpack(order + "3d", head[112:136]), dtype=np.float64)
            break
    else:
        return  # not a NIfTI header: SimpleITK reports it
    if not np.all(np.isfinite(pixdim)) or np.any(pixdim == 0):
        raise ValueError(
            f"`path`: {path!r} has voxel sizes (pixdim[1:4]) {pixdim.tolist()}; each must be a "
            "finite non-zero number"
        )
    if np.any(pixdim < 0):
        # The standard wants them positive (handedness is qfac's, pixdim[0]); ITK and
        # nibabel place such a file differently (8 mm apart on a 6-voxel test volume).
        raise ValueError(
            f"`path`: {path!r} has voxel sizes (pixdim[1:4]) {pixdim.tolist()}; the NIfTI "
            "standard wants them positive (the qform's handedness is pixdim[0]) and readers "
            "disagree on where a negative one puts the voxels: rewrite the header with "
            "positive sizes"
        )


def _space_voxels_by_the_sform(image: Any, path: str, header: tuple[str, bytes] | None) -> None:
    """Give ``image`` the voxel sizes of its NIfTI-1 sform where ITK placed it by the sform.

    ITK takes the direction and origin from the sform (when its code is 1, or the qform has
    none) but the voxel sizes from ``pixdim``; a file whose sform carries the geometry and
    whose ``pixdim`` was left at 1 (nibabel writes such files when only the sform is set)
    would be scaled silently. The NIfTI standard places voxels by the sform's columns.
    ``header``: :func:`_nifti1_header`'s.
    """
    if header is None:
        return
    order, head = header
    qform_code, sform_code = struct.unpack(order + "2h", head[252:256])
    if sform_code <= 0 or (sform_code != 1 and qform_code > 0):
        return  # placed by the qform (or by pixdim alone): pixdim is its voxel size
    sform = np.array(struct.unpack(order + "12f", head[280:328]), dtype=np.float64).reshape(3, 4)
    # ITK converts the spatial units (xyzt_units, bits 0-2) to millimetres.
    unit = {1: 1000.0, 3: 1e-3}.get(head[123] & 7, 1.0)
    sizes = np.linalg.norm(sform[:, :3], axis=0) * unit
    read = np.asarray(image.GetSpacing(), dtype=np.float64)
    if read.size < 3 or not np.all(sizes > 0) or np.allclose(sizes, read[:3], rtol=1e-4):
        return  # a 2D image has no third column to compare; a 4D one keeps its time step
    logger.warning(
        "%s: the NIfTI header's voxel sizes (pixdim %s mm) differ from those of the sform "
        "that places the volume (%s mm); read with the sform's, as the NIfTI standard places "
        "the voxels",
        path,
        np.round(read[:3], 6).tolist(),
        np.round(sizes, 6).tolist(),
    )
    image.SetSpacing([*sizes.tolist(), *read[3:].tolist()])


def _nifti1_header(head: bytes) -> tuple[str, bytes] | None:
    """The byte order and the 348 bytes of a NIfTI-1 header at the start of ``head``
    (``None`` for anything else)."""
    for order in ("<", ">"):
        if len(head) >= 348 and struct.unpack(order + "i", head[:4])[0] == 348:
            return order, head[:348]
    return None


def _warn_if_qform_and_sform_differ(path: str, header: tuple[str, bytes] | None) -> None:
    """Log a warning when a NIfTI-1 header holds a qform and an sform that place the volume
    differently: ITK (and so o3dreg) places it by the sform when its code is 1 (scanner
    anatomy) and by the qform otherwise, other software by its own rule (nibabel by the sform
    whenever it has a code), so the same file can land in two places depending on the
    software. ``header``: :func:`_nifti1_header`'s."""
    if header is None:
        return  # NIfTI-2 or not NIfTI: nothing checked
    order, head = header
    qform_code, sform_code = struct.unpack(order + "2h", head[252:256])
    if qform_code <= 0 or sform_code <= 0:
        return
    qfac = struct.unpack(order + "f", head[76:80])[0]
    pixdim = np.array(struct.unpack(order + "3f", head[80:92]), dtype=np.float64)
    b, c, d, qx, qy, qz = struct.unpack(order + "6f", head[256:280])
    a = float(np.sqrt(max(0.0, 1.0 - (b * b + c * c + d * d))))
    rotation = np.array(
        [
            [a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
            [2 * (b * c + a * d), a * a + c * c - b * b - d * d, 2 * (c * d - a * b)],
            [2 * (b * d - a * c), 2 * (c * d + a * b), a * a + d * d - b * b - c * c],
        ]
    )
    scale = pixdim * np.array([1.0, 1.0, -1.0 if qfac < 0 else 1.0])
    qform = np.column_stack([rotation * scale, [qx, qy, qz]])
    sform = np.array(struct.unpack(order + "12f", head[280:328]), dtype=np.float64).reshape(3, 4)
    # Voxel (i, j, k) of the far corner, placed by each: how far apart the two placements are.
    corner = np.array(struct.unpack(order + "3h", head[42:48]), dtype=np.float64)
    points = np.array([[0, 0, 0, 1], [*corner, 1]], dtype=np.float64)
    gap = float(np.abs(points @ qform.T - points @ sform.T).max())
    if gap > 1e-3 * max(float(pixdim.max()), 1.0):
        used, other = ("sform", "qform") if sform_code == 1 else ("qform", "sform")
        logger.warning(
            "%s: the NIfTI header's qform and sform place the volume up to %.3g mm apart; it is "
            "read by the %s (ITK's rule: the sform when its code is 1, else the qform), while "
            "other software may use the %s: check which the scanner meant",
            path,
            gap,
            used,
            other,
        )


def _nifti_data_end(head: bytes, path: str) -> int | None:
    """Byte offset of the end of the voxel data from a NIfTI-1 or NIfTI-2 header."""
    for order in ("<", ">"):
        (sizeof_hdr,) = struct.unpack(order + "i", head[:4]) if len(head) >= 4 else (0,)
        if sizeof_hdr == 348 and len(head) >= 348:
            dims = struct.unpack(order + "8h", head[40:56])
            (bitpix,) = struct.unpack(order + "h", head[72:74])
            (offset,) = struct.unpack(order + "f", head[108:112])
            break
        if sizeof_hdr == 540 and len(head) >= 540:
            (bitpix,) = struct.unpack(order + "h", head[14:16])
            dims = struct.unpack(order + "8q", head[16:80])
            (offset,) = struct.unpack(order + "q", head[168:176])
            break
    else:
        return None
    ndim = dims[0]
    if not 1 <= ndim <= 7 or bitpix <= 0 or any(d < 0 for d in dims[1 : ndim + 1]):
        raise ValueError(f"`path`: {path!r} has an invalid NIfTI header (dim {list(dims)})")
    voxels = int(np.prod([max(d, 1) for d in dims[1 : ndim + 1]], dtype=np.int64))
    return int(offset) + voxels * bitpix // 8
