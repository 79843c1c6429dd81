"""A self-contained HTML report: every image is embedded (a base64 data URI), no external CSS/JS/fonts, so
the file opens offline and can be mailed around as one file.

    rep = Report("splattwin twin: tabletop")
    sec = rep.section("Reconstruction")
    sec.text("15 training views, 3000 iterations.")
    sec.table(["view", "PSNR", "SSIM"], rows)
    sec.image(array_or_png_path, caption="ground truth | render | error", photo=True)
    rep.save(twin / "report" / "index.html")

Picture format (`picture_bytes`): photographic pictures (photos, splat and MuJoCo renders, the
photo | render | error strips, thumbnails) are embedded as JPEG, flat-colour ones (masks, label maps
without a photo under them, colour keys, plots) as PNG. Measured (Nov 2026): the demo twin's report (15
views at 320x240, its 0.5 MB video included) 6.2 MB with every picture PNG, 2.5 MB so (2.4 MB with the
MuJoCo picture once, not twice); the real cake's unscaled twin 3.7 MB, 1.2 MB. The rule, in order:
- a picture with an alpha channel: PNG (JPEG has no alpha);
- the caller says what it is: `photo=True` JPEG, `photo=False` PNG (a plot of thin lines and text,
  which JPEG would blur even where it is smaller);
- otherwise (`photo=None`) from the content: at most `FLAT_MAX_COLOURS` distinct colours (a mask, a key, a
  label map): PNG, lossless and the smaller for flat colour; more (a photo, or labels blended over one):
  both encoded and the JPEG kept only when it is at most `JPEG_GAIN` of the PNG's bytes (lossy only where
  it pays).
JPEG at quality `JPEG_QUALITY` without chroma subsampling (4:4:4): a 1-px coloured outline or a key's
swatch keeps its colour instead of bleeding into its neighbours (4:2:0 halves the colour resolution).
"""

from __future__ import annotations

import base64
import html
import io as _io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from splattwin import io

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0;background:#f6f7f9;color:#1d2330}
header{background:#1d2330;color:#fff;padding:18px 32px}header h1{margin:0;font-size:22px}
header p{margin:4px 0 0;color:#b9c0cc;font-size:13px}
main{max-width:1200px;margin:0 auto;padding:16px 32px 48px}
section{background:#fff;border-radius:8px;box-shadow:0 1px 3px rgba(0,0,0,.08);margin:18px 0;padding:16px 22px}
h2{font-size:18px;margin:0 0 10px;border-bottom:1px solid #e3e6eb;padding-bottom:6px}
table{border-collapse:collapse;margin:8px 0 12px;font-size:13px}
th,td{border:1px solid #e3e6eb;padding:4px 10px;text-align:right}th{background:#f0f2f5}
td:first-child,th:first-child{text-align:left}
figure{display:inline-block;margin:6px 10px 10px 0;vertical-align:top}
figure img{max-width:100%;border:1px solid #e3e6eb;border-radius:4px;image-rendering:auto}
figcaption{font-size:12px;color:#5b6475;margin-top:2px}
.kpis{display:flex;flex-wrap:wrap;gap:12px}.kpi{background:#f0f4ff;border-radius:6px;padding:8px 14px}
.kpi b{display:block;font-size:20px}.kpi span{font-size:12px;color:#5b6475}
video{max-width:100%;border:1px solid #e3e6eb;border-radius:4px}
.ok{color:#137333;font-weight:600}.bad{color:#b3261e;font-weight:600}pre{background:#f0f2f5;padding:8px;overflow:auto;font-size:12px}
"""


JPEG_QUALITY = 90   # photographic pictures (module docstring): ~40 dB PSNR on a photo, ~1/4 of the PNG bytes
FLAT_MAX_COLOURS = 256  # at most this many distinct colours: a flat-colour picture, kept PNG (lossless)
JPEG_GAIN = 0.75    # photo=None: the JPEG is kept only when at most this fraction of the PNG's bytes


def _as_uint8(image: np.ndarray) -> np.ndarray:
    """HxW(xC) uint8 of an array of uint8, or of floats in [0, 1] (clipped)."""
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = (np.clip(arr, 0, 1) * 255 + 0.5).astype(np.uint8)
    return arr


def png_bytes(image: np.ndarray | str | Path) -> bytes:
    """PNG bytes of an HxW(x3|4) array (uint8, or float in [0,1]) or of an existing image file."""
    from PIL import Image

    if isinstance(image, (str, Path)):
        from splattwin.limits import image_size, read_image_array

        w, h = image_size(image)  # header checked (size limit) before anything is decoded or embedded
        path = Path(image)
        with open(path, "rb") as f:
            png = f.read(8) == b"\x89PNG\r\n\x1a\n"
        # a PNG is embedded as it is when its file is no larger than its pixels could need (RGBA, 16-bit, no
        # compression, + 1 MiB); a small picture with gigabytes appended (after IEND, or in ancillary chunks)
        # was read and base64-embedded whole: it is decoded and written again instead
        if png and path.stat().st_size <= 8 * w * h + (1 << 20):
            return path.read_bytes()
        image = read_image_array(image, mode="RGB")
    buf = _io.BytesIO()
    Image.fromarray(_as_uint8(image)).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def jpeg_bytes(image: np.ndarray) -> bytes:
    """JPEG bytes (quality `JPEG_QUALITY`, 4:4:4: no chroma subsampling) of an HxW or HxWx3 array (uint8, or
    float in [0,1])."""
    from PIL import Image

    buf = _io.BytesIO()
    Image.fromarray(_as_uint8(image)).save(buf, format="JPEG", quality=JPEG_QUALITY, subsampling=0, optimize=True)
    return buf.getvalue()


def _decoded(path: str | Path) -> tuple[np.ndarray | None, bytes | None]:
    """(the picture as an HxW or HxWx3 uint8 array, None) of an image file without transparency, else (None,
    its PNG bytes: the file's own when it is a PNG). The size is checked before it is decoded."""
    from splattwin.limits import open_image, read_image_array

    with open_image(path) as im:
        alpha = bool({"A", "a"} & set(im.getbands())) or "transparency" in im.info
    if alpha:
        return None, png_bytes(path)
    return read_image_array(path, mode="RGB"), None


def _flat(arr: np.ndarray) -> bool:
    """At most `FLAT_MAX_COLOURS` distinct colours (PIL counts them, stopping once past the limit)."""
    from PIL import Image

    return Image.fromarray(arr).getcolors(FLAT_MAX_COLOURS) is not None


def picture_bytes(image: np.ndarray | str | Path, photo: bool | None = None) -> tuple[str, bytes]:
    """(MIME type, bytes) of a picture to embed: JPEG or PNG by the rule of the module docstring. image: an
    HxW(x3|4) array (uint8, or float in [0,1]) or an image file; photo: True photographic, False flat
    colour / a plot, None decided from the content."""
    if isinstance(image, (str, Path)):
        if photo is False:
            return "image/png", png_bytes(image)
        arr, png = _decoded(image)
        if arr is None:              # transparency
            return "image/png", png
    else:
        arr = _as_uint8(image)
        if photo is False or (arr.ndim == 3 and arr.shape[2] not in (1, 3)):   # a plot, or alpha (RGBA, LA)
            return "image/png", png_bytes(arr)
    arr = arr[..., 0] if arr.ndim == 3 and arr.shape[2] == 1 else arr
    if photo:
        return "image/jpeg", jpeg_bytes(arr)
    png = png_bytes(image if isinstance(image, (str, Path)) else arr)
    if _flat(arr):
        return "image/png", png
    jpg = jpeg_bytes(arr)
    return ("image/jpeg", jpg) if len(jpg) <= JPEG_GAIN * len(png) else ("image/png", png)


def data_uri(image: np.ndarray | str | Path, photo: bool | None = None) -> str:
    """A data: URI of the picture (`picture_bytes`: JPEG or PNG)."""
    mime, data = picture_bytes(image, photo)
    return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return '<span class="ok">yes</span>' if v else '<span class="bad">no</span>'
    if isinstance(v, (float, np.floating)):
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.3e}"
    return html.escape(str(v))


@dataclass
class Section:
    title: str
    parts: list[str] = field(default_factory=list)

    def text(self, s: str) -> "Section":
        self.parts.append(f"<p>{html.escape(s)}</p>")
        return self

    def pre(self, s: str) -> "Section":
        self.parts.append(f"<pre>{html.escape(s)}</pre>")
        return self

    def kpis(self, items: dict[str, Any]) -> "Section":
        cells = "".join(f'<div class="kpi"><b>{_fmt(v)}</b><span>{html.escape(k)}</span></div>' for k, v in items.items())
        self.parts.append(f'<div class="kpis">{cells}</div>')
        return self

    def table(self, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> "Section":
        head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
        body = "".join("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in r) + "</tr>" for r in rows)
        self.parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
        return self

    def image(self, image: np.ndarray | str | Path, caption: str = "", width: int | None = None,
              photo: bool | None = None) -> "Section":
        """Embed a picture (array or image file; width: shown width, px). photo: True for photographic
        content (JPEG), False for flat colour or a plot (PNG), None: decided from the content (module
        docstring)."""
        w = f' style="width:{int(width)}px"' if width else ""
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        src = data_uri(image, photo)
        self.parts.append(f'<figure><img{w} src="{src}" alt="{html.escape(caption)}">{cap}</figure>')
        return self

    def video(self, path: str | Path, caption: str = "", width: int | None = None,
              max_bytes: int = 64 << 20) -> "Section":
        """Embed an MP4 file (base64 data URI: the report stays one self-contained file)."""
        from splattwin.errors import InputError

        path = Path(path)
        size = path.stat().st_size
        if size > max_bytes:
            raise InputError(f"video of {size} bytes is too large to embed (at most {max_bytes})", path)
        data = base64.b64encode(path.read_bytes()).decode("ascii")
        w = f' width="{int(width)}"' if width else ""
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        self.parts.append(f'<figure><video controls loop muted playsinline{w} src="data:video/mp4;base64,{data}">'
                          f"</video>{cap}</figure>")
        return self


@dataclass
class Report:
    title: str
    subtitle: str = ""
    sections: list[Section] = field(default_factory=list)

    def section(self, title: str) -> Section:
        s = Section(title)
        self.sections.append(s)
        return s

    def to_html(self) -> str:
        body = "".join(f"<section><h2>{html.escape(s.title)}</h2>{''.join(s.parts)}</section>" for s in self.sections)
        return (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{html.escape(self.title)}</title>'
                f"<style>{_CSS}</style></head><body><header><h1>{html.escape(self.title)}</h1>"
                f"<p>{html.escape(self.subtitle)}</p></header><main>{body}</main></body></html>")

    def save(self, path: str | Path) -> Path:
        return io.write_text(path, self.to_html())


