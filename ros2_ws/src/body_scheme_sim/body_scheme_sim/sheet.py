"""Printable marker sheets: every marker of a placement at true scale, with its id, size and link, and cut lines.

A page is an image at ``dpi`` dots per inch (A4 by default). Each marker is drawn as on its simulated plate: the
black ArUco square of the marker's size, exactly ``round(size * dpi / 0.0254)`` dots wide, inside a one-cell white
quiet zone, surrounded by a dashed cut line; the label below names the id, the size in mm and the link. The tags of
a flat plate (markers with one ``plate`` key, in one plane and turned alike: an ArUco grid board) are printed as one
piece, each at its place on the plate, so the spacing the tracker assumes is the printed one; the tags of a plate
that is not flat (a cube with a tag per face) are printed one by one, labelled with their plate. The PDF holds the
same pages with their resolution recorded, so a printer at "actual size" (not "fit to page") prints the squares at
the given size; the PNG is page 1 (or every page, numbered), for checking on screen.
"""

from __future__ import annotations

import pathlib

import cv2
import numpy as np

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.plates import plates_from_markers

from .markers import MARKER_CELLS, marker_image

__all__ = ["A4_MM", "marker_pixels", "plate_face", "pieces", "sheet_pages", "write_sheet"]

#: Page size, mm (width, height).
A4_MM = (210.0, 297.0)
_MARGIN_MM = 10.0
_GAP_MM = 6.0
_LABEL_MM = 6.0
#: A plate's tags are printed as one piece when each lies within this of the reference tag's plane (m) and is
#: turned like it (rad).
_FLAT_M, _FLAT_RAD = 2e-4, 1e-3


def marker_pixels(size, dpi):
    """Dots across a marker's black square of edge ``size`` (m) at ``dpi``."""
    return int(round(size / 0.0254 * dpi))


def _square(marker, dots_per_m):
    square = marker_pixels(marker.size, dots_per_m * 0.0254)
    if square < 2 * MARKER_CELLS:
        raise InvalidInputError(f"marker {marker.id}: {marker.size} m is {square} dots at "
                                f"{dots_per_m * 0.0254:.0f} dpi; too small to print")
    return square


def plate_face(markers, centres, dots_per_m, patterns=True):
    """The face of a plate (or of one marker's own plate): each marker's square at its centre (``centres``: (x right,
    y up) m in the plate's frame) in its one-cell white quiet zone, on white cropped to the quiet zones; with
    ``patterns`` False the squares are plain black (any id).

    Returns
    -------
    image : ndarray (height, width), uint8
    placed : dict
        ``{id: ((row, column) of the square's top-left dot, square dots)}``.
    centre : (float, float)
        Where the image's centre is in the plate's frame, m (x, y).

    Raises
    ------
    InvalidInputError
        A square too small for the resolution, or on another marker's square or quiet zone (neighbours may share
        their white).
    """
    squares = {m.id: _square(m, dots_per_m) for m in markers}
    boxes = {}  # id: (top, left) of the square with its quiet zone, dots from the plate's origin
    for m in markers:
        half = 0.5 * squares[m.id] + int(round(squares[m.id] / MARKER_CELLS))
        x, y = (float(v) * dots_per_m for v in centres[m.id])
        boxes[m.id] = (-y - half, x - half, -y + half, x + half)
    top, left = min(b[0] for b in boxes.values()), min(b[1] for b in boxes.values())
    bottom, right = max(b[2] for b in boxes.values()), max(b[3] for b in boxes.values())
    image = np.full((int(round(bottom - top)), int(round(right - left))), 255, dtype=np.uint8)
    placed, black, quiet_zones = {}, np.zeros(image.shape, dtype=bool), np.zeros(image.shape, dtype=bool)
    for m in markers:
        square, quiet = squares[m.id], int(round(squares[m.id] / MARKER_CELLS))
        row, column = (int(round(v - o)) + quiet for v, o in zip(boxes[m.id][:2], (top, left), strict=True))
        zone = (slice(row - quiet, row + square + quiet), slice(column - quiet, column + square + quiet))
        inner = (slice(row, row + square), slice(column, column + square))
        if black[zone].any() or quiet_zones[inner].any():
            raise InvalidInputError(f"marker {m.id} overlaps another of its plate or its white border: move it")
        black[inner] = quiet_zones[zone] = True
        image[inner] = marker_image(m.id, square) if patterns else 0
        placed[m.id] = ((row, column), square)
    return image, placed, (0.5 * (left + right) / dots_per_m, -0.5 * (top + bottom) / dots_per_m)


def pieces(markers):
    """``[(id, markers, {id: centre (x, y) m})]``: what is printed and drawn as one piece, in its own frame. A flat
    plate (one ``plate`` key, its tags in one plane and turned alike: an ArUco grid board) is one piece under the
    plate's id, its tags at their places; every other marker is a piece of its own, centred."""
    markers = list(markers)
    found, placed = [], set()
    for plate_id, plate in plates_from_markers(markers).items():
        if all(abs(T[2, 3]) <= _FLAT_M and np.allclose(T[:3, :3], np.eye(3), atol=_FLAT_RAD)
               for _, T in plate.tags.values()):
            members = sorted((m for m in markers if m.plate == plate_id), key=lambda m: m.id)
            found.append((plate_id, members, {m.id: plate.tags[m.id][1][:2, 3] for m in members}))
            placed.update(m.id for m in members)
    return found + [(m.id, [m], {m.id: (0.0, 0.0)}) for m in markers if m.id not in placed]


def _tile(markers, centres, dpi, text):
    """One piece to cut out: :func:`plate_face` with the dashed cut line around it and ``text`` below; ``(image,
    {id: (row, column) of the square's top-left dot within the tile, square dots})``."""
    face, placed, _ = plate_face(markers, centres, dpi / 0.0254)
    height, width = face.shape
    label = int(round(_LABEL_MM / 25.4 * dpi))
    tile = np.full((height + label + 2, width + 2), 255, dtype=np.uint8)
    tile[1:1 + height, 1:1 + width] = face
    dash = max(2, int(round(dpi / 25.4 * 2)))  # 2 mm dashes
    for k in range(0, max(height, width) + 2, 2 * dash):  # the cut line on the piece's outline
        tile[0, k:min(k + dash, width + 2)] = tile[height + 1, k:min(k + dash, width + 2)] = 128
        tile[k:min(k + dash, height + 2), 0] = tile[k:min(k + dash, height + 2), width + 1] = 128
    scale = 0.5 * label / 22.0
    cv2.putText(tile, text, (2, height + 2 + int(0.75 * label)), cv2.FONT_HERSHEY_SIMPLEX, scale, 0,
                max(1, int(round(scale * 1.5))), cv2.LINE_AA)
    return tile, {k: ((row + 1, column + 1), square) for k, ((row, column), square) in placed.items()}


def _label(members):
    """What is printed under a piece: a marker's id, size and link, or a plate's id, tags, size and link."""
    m = members[0]
    if len(members) == 1:
        return f"id {m.id}  {m.size * 1000:.0f} mm  {m.link}" + (f"  plate {m.plate}" if m.plate is not None else "")
    sizes = "/".join(str(size) for size in sorted({round(t.size * 1000) for t in members}))
    return f"plate {m.plate}: {len(members)} tags {sizes} mm  {m.link}"


def sheet_pages(markers, dpi=300, page_mm=A4_MM):
    """Pages of markers at true scale, laid out in rows.

    Parameters
    ----------
    markers : iterable of Marker
    dpi : int
    page_mm : (float, float)

    Returns
    -------
    pages : list of ndarray, dtype uint8 (height, width)
    boxes : list of (page, marker id, (row, column) of the square's top-left dot, square dots)
    """
    if not (isinstance(dpi, int) and 72 <= dpi <= 1200):
        raise InvalidInputError(f"dpi must be an integer in 72..1200, got {dpi!r}")
    width, height = (int(round(v / 25.4 * dpi)) for v in page_mm)
    margin, gap = (int(round(v / 25.4 * dpi)) for v in (_MARGIN_MM, _GAP_MM))
    pages, boxes = [], []
    x = y = row_height = 0
    tiles = [(_tile(members, centres, dpi, _label(members)), members) for _, members, centres in pieces(markers)]
    for (tile, placed), members in sorted(tiles, key=lambda t: (-t[0][0].size, min(m.id for m in t[1]))):
        h, w = tile.shape
        if w > width - 2 * margin or h > height - 2 * margin:
            what = f"marker {members[0].id} ({members[0].size} m)" if len(members) == 1 else \
                f"plate {members[0].plate}"
            raise InvalidInputError(f"{what} does not fit on a {page_mm} mm page")
        if not pages or x + w > width - margin:
            x, y, row_height = margin, (y + row_height + gap) if pages else margin, 0
        if not pages or y + h > height - margin:
            pages.append(np.full((height, width), 255, dtype=np.uint8))
            x, y, row_height = margin, margin, 0
        pages[-1][y:y + h, x:x + w] = tile
        for marker_id, ((row, column), square) in sorted(placed.items()):
            boxes.append((len(pages) - 1, marker_id, (y + row, x + column), square))
        x += w + gap
        row_height = max(row_height, h)
    return pages, boxes


def write_sheet(markers, stem, dpi=300, page_mm=A4_MM):
    """Write ``<stem>.pdf`` (every page, true scale) and ``<stem>.png`` (``<stem>-<k>.png`` for more pages).

    Returns
    -------
    paths : list of pathlib.Path
    """
    from PIL import Image

    pages, _ = sheet_pages(markers, dpi, page_mm)
    stem = pathlib.Path(stem)
    images = [Image.fromarray(page) for page in pages]
    pdf = stem.with_name(stem.name + ".pdf")  # a stem may hold dots: my.markers -> my.markers.pdf
    images[0].save(pdf, save_all=True, append_images=images[1:], resolution=float(dpi))
    paths = [pdf]
    for k, image in enumerate(images):
        png = stem.with_name(f"{stem.name}.png" if len(images) == 1 else f"{stem.name}-{k + 1}.png")
        image.save(png, dpi=(dpi, dpi))
        paths.append(png)
    return paths
