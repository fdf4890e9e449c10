"""Printable marker sheets: every marker of a placement at true scale, with its id, size and link, and cut lines.

A page is an image at ``dpi`` dots per inch (A4 by default). Each marker is drawn as on its simulated plate: the
black ArUco square of the marker's size, exactly ``round(size * dpi / 0.0254)`` dots wide, inside a one-cell white
quiet zone, surrounded by a dashed cut line; the label below names the id, the size in mm and the link. The PDF
holds the same pages with their resolution recorded, so a printer at "actual size" (not "fit to page") prints the
squares at the given size; the PNG is page 1 (or every page, numbered), for checking on screen.
"""

from __future__ import annotations

import pathlib

import cv2
import numpy as np

from body_scheme_core.errors import InvalidInputError

from .markers import MARKER_CELLS, aruco_dictionary

__all__ = ["A4_MM", "marker_pixels", "sheet_pages", "write_sheet"]

#: Page size, mm (width, height).
A4_MM = (210.0, 297.0)
_MARGIN_MM = 10.0
_GAP_MM = 6.0
_LABEL_MM = 6.0


def marker_pixels(size, dpi):
    """Dots across a marker's black square of edge ``size`` (m) at ``dpi``."""
    return int(round(size / 0.0254 * dpi))


def _tile(marker, dpi):
    """One marker's tile: quiet zone, square, dashed cut line and label; ``(image, square_px)``."""
    square = marker_pixels(marker.size, dpi)
    if square < 2 * MARKER_CELLS:
        raise InvalidInputError(f"marker {marker.id}: {marker.size} m is {square} dots at {dpi} dpi; too small to "
                                f"print")
    cell = square / MARKER_CELLS
    quiet = int(round(cell))
    label = int(round(_LABEL_MM / 25.4 * dpi))
    side = square + 2 * quiet
    tile = np.full((side + label + 2, side + 2), 255, dtype=np.uint8)
    pattern = cv2.aruco.generateImageMarker(aruco_dictionary(), marker.id, square)
    tile[1 + quiet:1 + quiet + square, 1 + quiet:1 + quiet + square] = pattern
    dash = max(2, int(round(dpi / 25.4 * 2)))  # 2 mm dashes
    for k in range(0, side + 2, 2 * dash):  # the cut line on the plate's outline
        tile[0, k:k + dash] = tile[side + 1, k:k + dash] = 128
        tile[k:k + dash, 0] = tile[k:k + dash, side + 1] = 128
    text = f"id {marker.id}  {marker.size * 1000:.0f} mm  {marker.link}"
    scale = 0.5 * label / 22.0
    cv2.putText(tile, text, (2, side + 2 + int(0.75 * label)), cv2.FONT_HERSHEY_SIMPLEX, scale, 0,
                max(1, int(round(scale * 1.5))), cv2.LINE_AA)
    return tile, square


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
    for marker in sorted(markers, key=lambda m: (-m.size, m.id)):
        tile, square = _tile(marker, dpi)
        h, w = tile.shape
        if w > width - 2 * margin or h > height - 2 * margin:
            raise InvalidInputError(f"marker {marker.id} ({marker.size} m) does not fit on a {page_mm} mm page")
        if not pages or x + w > width - margin:
            x, y, row_height = margin, (y + row_height + gap) if pages else margin, 0
        if not pages or y + h > height - margin:
            pages.append(np.full((height, width), 255, dtype=np.uint8))
            x, y, row_height = margin, margin, 0
        pages[-1][y:y + h, x:x + w] = tile
        quiet = int(round(square / MARKER_CELLS))
        boxes.append((len(pages) - 1, marker.id, (y + 1 + quiet, x + 1 + quiet), square))
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
    pdf = stem.with_suffix(".pdf")
    images[0].save(pdf, save_all=True, append_images=images[1:], resolution=float(dpi))
    paths = [pdf]
    for k, image in enumerate(images):
        png = stem.with_suffix(".png") if len(images) == 1 else stem.with_name(f"{stem.name}-{k + 1}.png")
        image.save(png, dpi=(dpi, dpi))
        paths.append(png)
    return paths
