"""
Compressed images (``sensor_msgs/CompressedImage``, image_transport ``compressed``) <-> grey.

The ``format`` field written by image_transport's compressed plugin reads
``"<encoding>; <codec> compressed <coded encoding>"``, for example ``"mono8; jpeg compressed
mono8"``, ``"rgb8; jpeg compressed bgr8"`` or ``"mono16; png compressed mono16"``; older
drivers write just ``"jpeg"`` or ``"png"``. The coded image is a complete JPEG or PNG file,
decoded here with OpenCV: colour is stored in OpenCV's BGR order (``bgr8``, also for an
``rgb8`` source, which the plugin converts before coding) unless the coded encoding says
``rgb8``. Depth images (``compressedDepth``) are not camera images and are refused.

No ROS import: used by the node (``ros.image_transport: compressed``) and by the bag reader.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..errors import ImageError

#: Codecs this module decodes and writes.
CODECS = ('jpeg', 'png')
#: Coded encodings (after "compressed") and the OpenCV conversion of their decoded pixels.
_CODED_TO_GREY = {'bgr8': cv2.COLOR_BGR2GRAY, 'rgb8': cv2.COLOR_RGB2GRAY,
                  'bgra8': cv2.COLOR_BGRA2GRAY, 'rgba8': cv2.COLOR_RGBA2GRAY}


def parse_format(fmt: str) -> tuple[str, str]:
    """
    Read the codec and the coded encoding of a CompressedImage ``format`` field.

    Returns
    -------
    tuple of str
        ``(codec, coded_encoding)``: codec ``jpeg`` or ``png``; the coded encoding is ``''``
        when the field does not name it (plain ``"jpeg"``).

    Raises
    ------
    ImageError
        The field names another codec or compressedDepth.

    """
    text = str(fmt).strip().lower()
    if 'compresseddepth' in text:
        raise ImageError(f'compressed image format {fmt!r} is a depth image (compressedDepth); '
                         'the odometry needs camera images')
    coded = ''
    if ';' in text:
        _, _, rest = text.partition(';')
        words = rest.split()
        codec = words[0] if words else ''
        if 'compressed' in words and words.index('compressed') + 1 < len(words):
            coded = words[words.index('compressed') + 1]
    else:
        codec = text
    codec = {'jpg': 'jpeg'}.get(codec, codec)
    if codec not in CODECS:
        raise ImageError(f'unsupported compressed image format {fmt!r}; supported codecs: '
                         f'{list(CODECS)}')
    return codec, coded


def grey_from_compressed(fmt: str, data: Any) -> np.ndarray:
    """
    Decode a compressed camera image to grey.

    Parameters
    ----------
    fmt : str
        The message's ``format`` field (see the module docstring).
    data : bytes-like or np.ndarray
        The coded image (the message's ``data``).

    Returns
    -------
    np.ndarray
        (H, W) uint8 grey image, or uint16 for a 16-bit PNG.

    Raises
    ------
    ImageError
        Unsupported format, empty data, or data that OpenCV cannot decode.

    """
    codec, coded = parse_format(fmt)
    if isinstance(data, np.ndarray):
        buf = data.reshape(-1).view(np.uint8)
    else:
        buf = np.frombuffer(memoryview(data).cast('B'), np.uint8)
    if buf.size == 0:
        raise ImageError(f'compressed image ({fmt!r}) has no data')
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ImageError(f'compressed image ({fmt!r}, {buf.size} bytes) cannot be decoded as '
                         f'{codec}')
    if img.ndim == 2:
        return img
    if img.shape[2] == 1:
        return np.ascontiguousarray(img[:, :, 0])
    if img.shape[2] == 4:
        code = _CODED_TO_GREY['rgba8' if coded in ('rgba8', 'rgb8') else 'bgra8']
    else:
        code = _CODED_TO_GREY['rgb8' if coded == 'rgb8' else 'bgr8']
    return cv2.cvtColor(img, code)


def compress_grey(img: np.ndarray, codec: str = 'jpeg', quality: int = 90
                  ) -> tuple[str, np.ndarray]:
    """
    Code a grey image as image_transport's compressed plugin does.

    Parameters
    ----------
    img : np.ndarray
        (H, W) uint8 grey image (uint16 allowed for png).
    codec : str
        ``jpeg`` or ``png``.
    quality : int
        JPEG quality 1..100 (ignored for png).

    Returns
    -------
    tuple
        ``(format, data)``: the ``format`` field (``"mono8; jpeg compressed mono8"``) and the
        coded bytes as a (K,) uint8 array.

    Raises
    ------
    ImageError
        Unknown codec, a 16-bit image for jpeg, or a failed encode.

    """
    if codec not in CODECS:
        raise ImageError(f'codec must be one of {list(CODECS)}, got {codec!r}')
    img = np.asarray(img)
    encoding = 'mono16' if img.dtype == np.uint16 else 'mono8'
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16) or \
            (codec == 'jpeg' and img.dtype != np.uint8):
        raise ImageError(f'{codec} needs a 2-D uint8 image (png also uint16), got '
                         f'{img.dtype} {img.shape}')
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if codec == 'jpeg' else \
        [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, buf = cv2.imencode('.jpg' if codec == 'jpeg' else '.png', img, params)
    if not ok:
        raise ImageError(f'{codec} encoding of a {img.shape} image failed')
    return f'{encoding}; {codec} compressed {encoding}', buf.reshape(-1)
