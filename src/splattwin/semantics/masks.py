"""`MaskSet`: 2D object masks per view and object label, from any source, behind one interface.

A MaskSet holds, for each view (image stem, e.g. "train_003") and each object label (int >= 1, 0 is
background), a boolean mask [H,W] in that view's image pixels plus a detector/segmenter score in [0,1].
Object names and prompts are kept per label. It loads and saves itself (`save(dir)` / `MaskSet.load(dir)`).

Accepted sources (`load_masks` picks by what it finds):
- MaskSet folders written by `save`: `masks.json` index + `<view>/<object>.png`.
- PNG per view and object: `<dir>/<view>/<object>.png` (non-zero = inside), e.g. the embedded scene's
  `masks/noisy`; labels come from `objects` (name -> label) or are assigned 1..K by sorted name.
- Label images: `<dir>/<view>.png`, uint8/uint16 pixel = object label (0 background), e.g. `masks/gt`.
- COCO JSON (one file): `images[{id, file_name, height, width}]`, `categories[{id, name}]`,
  `annotations[{image_id, category_id, segmentation, score?}]` where segmentation is RLE
  (compressed string or list counts, see `splattwin.semantics.rle`) or polygons `[[x1, y1, x2, y2, ...]]`.
  Several annotations of one category in one image are merged (union, max score).
- Per-instance mask files, one binary image per object instance and view:
  - a BOP scene (`scene_gt.json` + `mask_visib/` or `mask/`, files `{image:06d}_{instance:06d}.png`): give
    the scene folder (visible masks `mask_visib/` preferred) or the mask folder itself. The instance's
    object is its `obj_id` in `scene_gt.json`, named by `splattwin.capture.bop.object_names`
    (`object_names.json`, or `obj_000001`). Several instances of one `obj_id` are told apart by their
    positions in the world when the scene has camera poses (else by their order in each image's list)
    and named `<name>`, `<name>_2`, ...
  - `<dir>/<view>_<instance>.png` with `<dir>/instances.json` naming the instances
    (`{"1": "mug", "2": "bowl"}`; without it `instance_1`, ...). The layout is recognised by the
    `instances.json` file, or, when the dataset's views are known, by file names that are a view name
    plus `_<number>`.
- Polygon JSON of the paper's published code (github.com/535A59/3DGS-Digital-Twin,
  `src/semantic_segmentation/sam_segmentation.py`): one file per image named `<stem>_mask.json` with
  `{"image_filename", "image_height", "image_width", "input_points", "input_labels",
  "segmentation_polygons": [[[x, y], ...], ...]}` (OpenCV contours, pixel coordinates), one object per
  folder: either `<dir>/<object>/<stem>_mask.json` or `<dir>/<stem>_mask.json` for a single object
  (named after the folder, or an optional `"object"` key). Rasterised with `cv2.fillPoly` like the
  published loader.

Every loader treats its files as untrusted (they are often received from someone else): object and
view names are checked where they enter (`splattwin.names`: never a path, unique), paths in a
`masks.json` index and files found by listing a mask folder stay inside it, symbolic links resolved
(`splattwin.paths`), every image or mask size read from a file is checked against `splattwin.limits`
before a pixel is allocated, and a view holds at most `MAX_OBJECTS_PER_VIEW` objects. With
`image_sizes` (view -> (H, W) of the dataset's images) each mask is checked against its own image as it
is read, so a wrong-size file is named, not the object whose mask happened to be read first.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from splattwin import io
from splattwin.errors import InputError, short_repr
from splattwin.limits import ascii_uint, check_pixels, read_image_array
from splattwin.names import check_unique, name_from_label, object_name, view_name
from splattwin.paths import child, confined
from splattwin.semantics import rle as rle_codec

log = logging.getLogger(__name__)

INDEX_NAME = "masks.json"
MAX_LABEL_ID = 65535   # label images are at most 16-bit: an id above cannot be drawn (nor sizes an array)
# Objects in one view (distinct values of a label image, instances of a BOP image): a scene has tens.
# Each costs a full-size mask (and a PNG when saved), so a few bytes of file must not claim thousands.
MAX_OBJECTS_PER_VIEW = 1000
MAX_CATEGORIES = 10_000    # COCO categories (LVIS has 1203); more is not a label set
MAX_ID = 2**63 - 1         # COCO image and category ids: whole numbers that fit an int64
_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class MaskWarning(UserWarning):
    """A mask problem that does not stop the run (e.g. an object missing from some views)."""


@dataclass
class MaskSet:
    """Per view, per object label: bool mask [H,W] (image pixels) + score in [0,1].

    objects: label -> object name (labels >= 1). prompts: label -> text prompt (optional).
    masks[view][label] -> bool [H,W]; scores[view][label] -> float. sizes[view] = (H, W) of the view's
    image (also for views where no object was found, so "seen in no view" can be told from "no view").
    source: free text saying where the masks came from.
    """

    objects: dict[int, str] = field(default_factory=dict)
    masks: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    scores: dict[str, dict[int, float]] = field(default_factory=dict)
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)
    prompts: dict[int, str] = field(default_factory=dict)
    source: str = ""
    # view -> the file whose mask set the view's size (named when another mask of the view differs)
    size_sources: dict[str, str] = field(default_factory=dict, repr=False, compare=False)

    def __eq__(self, other) -> bool:
        """Same objects, prompts, sizes, scores and masks (array-aware; `source` and where the sizes came
        from are not compared)."""
        if not isinstance(other, MaskSet):
            return NotImplemented
        if (self.objects != other.objects or self.prompts != other.prompts or self.scores != other.scores
                or {k: tuple(v) for k, v in self.sizes.items()} != {k: tuple(v) for k, v in other.sizes.items()}
                or self.masks.keys() != other.masks.keys()):
            return False
        for view, per in self.masks.items():
            theirs = other.masks[view]
            if per.keys() != theirs.keys() or not all(np.array_equal(m, theirs[k]) for k, m in per.items()):
                return False
        return True

    __hash__ = None  # mutable, like any dataclass with eq

    # -- access -------------------------------------------------------------------------------
    @property
    def views(self) -> list[str]:
        return sorted(set(self.sizes) | set(self.masks))

    @property
    def labels(self) -> list[int]:
        return sorted(self.objects)

    def label_of(self, name: str) -> int:
        for k, v in self.objects.items():
            if v == name:
                return k
        raise InputError(f"no object named {name!r} in the mask set (have: {', '.join(self.objects.values())})")

    def get(self, view: str, label: int) -> np.ndarray | None:
        """bool [H,W] mask of `label` in `view`, or None when the object was not found there."""
        return self.masks.get(view, {}).get(label)

    def add(self, view: str, label: int, mask: np.ndarray, score: float = 1.0, name: str | None = None,
            source: str | Path | None = None) -> None:
        """Add (or merge by union) a mask. `name` registers the object if the label is new. `source`:
        the file the mask came from (named in errors)."""
        raw = np.asarray(mask)
        if raw.dtype.kind == "f" and raw.size and not np.isin(raw, (0.0, 1.0)).all():
            raise InputError(f"mask for view {view!r}, label {label} holds float values other than 0 and 1 (a "
                             f"probability or soft mask? every non-zero value would count as inside): threshold it, "
                             f"e.g. mask > 0.5", source)
        mask = raw.astype(bool)
        if mask.ndim != 2:
            raise InputError(f"mask for view {view!r}, label {label} must be 2D, got shape {mask.shape}", source)
        if label < 1:
            raise InputError(f"object labels start at 1 (0 is background), got {label} for view {view!r}", source)
        if name is not None:
            self.objects.setdefault(label, name)
        elif label not in self.objects:
            self.objects[label] = f"object_{label}"
        size = self.sizes.setdefault(view, mask.shape)
        if source is not None:
            self.size_sources.setdefault(view, str(source))
        if tuple(size) != mask.shape:
            first = self.size_sources.get(view)
            other = f"the first mask of that view ({first})" if first and first != str(source) else "other masks of that view"
            raise InputError(f"mask of {self.objects[label]!r} in view {view!r} is {mask.shape[1]}x{mask.shape[0]} "
                             f"but {other} is {size[1]}x{size[0]}", source)
        per_view = self.masks.setdefault(view, {})
        if label in per_view:
            per_view[label] = per_view[label] | mask
            self.scores[view][label] = max(self.scores[view][label], float(score))
        else:
            per_view[label] = mask
            self.scores.setdefault(view, {})[label] = float(score)

    def n_views_with(self, label: int) -> int:
        return sum(1 for v in self.masks.values() if label in v and v[label].any())

    # -- checks -------------------------------------------------------------------------------
    def validate(self, image_sizes: dict[str, tuple[int, int]] | None = None, where: str | Path | None = None) -> None:
        """Raise InputError for an empty set or masks whose size differs from their image.

        image_sizes: view -> (H, W) of the images the masks belong to. Views without an image raise too.
        Objects found in no view raise (never a silently empty object).
        """
        if not self.objects or not any(m.any() for v in self.masks.values() for m in v.values()):
            raise InputError("empty mask set: no object mask with any pixel", where)
        for label, name in self.objects.items():
            if self.n_views_with(label) == 0:
                raise InputError(f"object {name!r} (label {label}) is seen in no view: its masks are all empty", where)
        if image_sizes is None:
            return
        for view, hw in self.sizes.items():
            if view not in image_sizes:
                raise InputError(f"masks for view {view!r} but the dataset has no image of that name "
                                 f"(have: {', '.join(sorted(image_sizes)[:6])}...)", where)
            if tuple(hw) != tuple(image_sizes[view]):
                H, W = image_sizes[view]
                raise InputError(f"masks of view {view!r} are {hw[1]}x{hw[0]} but its image is {W}x{H}"
                                 f"{_turned(hw, (H, W))}", where)

    # -- load / save --------------------------------------------------------------------------
    def save(self, out_dir: str | Path) -> Path:
        """Write `<out_dir>/<view>/<object>.png` (0/255) and the `masks.json` index (atomically)."""
        out_dir = Path(out_dir)
        index: dict = {"source": self.source,
                       "objects": [{"name": n, "label": int(k), "prompt": self.prompts.get(k, "")}
                                   for k, n in sorted(self.objects.items())],
                       "views": {}}
        for view in self.views:
            entry = {"size": list(self.sizes.get(view, ())), "masks": {}}
            vdir = child(out_dir, view_name(view), what="view name")
            for label, m in sorted(self.masks.get(view, {}).items()):
                rel = f"{view}/{object_name(self.objects[label])}.png"
                io.write_image(child(vdir, f"{self.objects[label]}.png"), (m.astype(np.uint8) * 255))
                entry["masks"][self.objects[label]] = {"file": rel, "score": self.scores[view][label]}
            index["views"][view] = entry
        io.write_json(out_dir / INDEX_NAME, index)
        return out_dir

    @classmethod
    def load(cls, path: str | Path, objects: dict[str, int] | None = None) -> "MaskSet":
        """Load any supported layout (see module docstring). objects: name -> label to use."""
        return load_masks(path, objects=objects)


# -- loaders ----------------------------------------------------------------------------------

def _entries(folder: Path) -> list[Path]:
    """The entries of `folder` without hidden ones (a leading dot): macOS writes an AppleDouble `._x.png`
    beside every file copied to a FAT/exFAT drive or share, which is no mask and stopped the masks as
    unreadable."""
    return [p for p in Path(folder).iterdir() if not p.name.startswith(".")]


def _glob(folder: Path, pattern: str) -> list[Path]:
    """`folder.glob(pattern)` without hidden files or files in hidden folders (see `_entries`)."""
    return [p for p in Path(folder).glob(pattern)
            if not any(part.startswith(".") for part in p.relative_to(folder).parts)]


def _turned(mask_hw, image_hw) -> str:
    """A hint when a mask has the image's size turned by 90 degrees."""
    if tuple(mask_hw) == tuple(image_hw)[::-1] and mask_hw[0] != mask_hw[1]:
        return (" (turned by 90 degrees: masks must match the photo as a viewer shows it, upright; a photo stored "
                "sideways with an EXIF Orientation tag is used upright)")
    return ""


def load_masks(path: str | Path, objects: dict[str, int] | None = None, object_name: str | None = None,
               image_sizes: dict[str, tuple[int, int]] | None = None) -> MaskSet:
    """Load masks from a MaskSet folder, PNG folder, label-image folder, COCO JSON or polygon JSON.

    objects: name -> label (e.g. from the scene's scene.json); unknown names get fresh labels.
    object_name: object name for a flat polygon-JSON folder (default: the folder name).
    image_sizes: view -> (H, W) of the dataset's images: every mask of such a view is checked against
    its image as it is read (InputError naming the mask file). Masks of views without an image are
    not checked here (fusion ignores them with a MaskWarning).
    """
    path = Path(path)
    if not path.exists():
        raise InputError("mask path does not exist", path)
    if path.is_file():
        if path.suffix.lower() != ".json":
            raise InputError("a mask file must be COCO JSON (or give a folder of PNG / polygon JSON masks)", path)
        data = io.read_json(path)
        if isinstance(data, dict) and "annotations" in data:
            return load_coco(path, objects, image_sizes)
        if isinstance(data, dict) and "segmentation_polygons" in data:
            return load_polygon_dir(path.parent, objects, object_name, image_sizes)
        raise InputError("JSON is neither COCO (annotations) nor polygon masks (segmentation_polygons)", path)
    if (path / INDEX_NAME).is_file():
        return load_maskset_dir(path, image_sizes)
    if find_bop_scene(path) is not None:
        return load_bop_masks(path, objects, image_sizes)
    if (path / INSTANCES_FILE).is_file() or _looks_per_instance(path, image_sizes):
        return load_instance_masks(path, objects, image_sizes)
    coco = [p for p in _glob(path, "*.json") if p.name != INDEX_NAME and _mentions_annotations(p)]
    if len(coco) == 1 and not list(_glob(path, "*_mask.json")):
        return load_coco(coco[0], objects, image_sizes)
    if list(_glob(path, "*_mask.json")) or list(_glob(path, "*/*_mask.json")):
        return load_polygon_dir(path, objects, object_name, image_sizes)
    if any(p.suffix.lower() in _IMAGE_EXTS for p in _entries(path) if p.is_file()):
        return load_label_images(path, objects, image_sizes)
    if any(p.is_dir() for p in _entries(path)):
        return load_png_dir(path, objects, image_sizes)
    raise InputError("no masks found (expected <view>/<object>.png, <view>.png label images, COCO JSON or "
                     "<image>_mask.json polygon files)", path)


def _mentions_annotations(p: Path) -> bool:
    with open(p, "rb") as f:
        return b"annotations" in f.read(100_000)


def _check_names(ms: MaskSet, where: Path) -> None:
    check_unique(ms.objects.values(), where)


def _check_image(view: str, hw: tuple[int, int], image_sizes: dict | None, where: Path) -> None:
    """The mask of `view` (size hw = (H, W)) against the dataset image of that view, if sizes are known."""
    if image_sizes is None or view not in image_sizes:
        return
    H, W = image_sizes[view]
    if tuple(hw) != (H, W):
        raise InputError(f"mask of view {view!r} is {hw[1]}x{hw[0]} but its image is {W}x{H}{_turned(hw, (H, W))}",
                         where)


def load_maskset_dir(path: Path, image_sizes: dict | None = None) -> MaskSet:
    index_path = path / INDEX_NAME
    index = io.read_json(index_path)
    try:
        ms = MaskSet(source=str(index.get("source", str(path))))
        by_name = {}
        for o in index["objects"]:
            name = object_name(o["name"], index_path)
            label = whole_number(o["label"], index_path, f"label of object {name!r}", 1, MAX_LABEL_ID)
            if label in ms.objects:
                raise InputError(f"object {name!r}: label {label} is used twice", index_path)
            ms.objects[label] = name
            if o.get("prompt"):
                ms.prompts[label] = str(o["prompt"])
            by_name[name] = label
        _check_names(ms, index_path)
        for view, entry in index["views"].items():
            view_name(view, index_path)
            size = None
            if entry.get("size"):
                h, w = entry["size"]
                w, h = check_pixels(w, h, index_path, f"view {view!r}")
                size = ms.sizes[view] = (h, w)
                _check_image(view, size, image_sizes, index_path)
            for name, m in entry["masks"].items():
                if name not in by_name:
                    raise InputError(f"view {view!r} names object {name!r} missing from the objects list", index_path)
                mpath = confined(path, m["file"], index_path, f"mask file of {name!r} in view {view!r}")
                score = _score(m.get("score", 1.0), index_path, f"score of {name!r} in view {view!r}")
                mask = _read_binary_png(mpath)
                # against the image first: a file that differs from its photo is the one to blame
                _check_image(view, mask.shape, image_sizes, mpath)
                if size is not None and mask.shape != size:  # the index's size is the claim that is wrong
                    raise InputError(f"{INDEX_NAME} says view {view!r} is {size[1]}x{size[0]} but its mask file "
                                     f"{m['file']} is {mask.shape[1]}x{mask.shape[0]}", index_path)
                _check_size(ms, view, mask, mpath)
                ms.add(view, by_name[name], mask, score, source=mpath)
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(f"malformed mask index: {e}", index_path) from e
    return ms


def load_png_dir(path: Path, objects: dict[str, int] | None = None, image_sizes: dict | None = None) -> MaskSet:
    """`<path>/<view>/<object>.png` -> MaskSet (non-zero pixels inside)."""
    labels = dict(objects or {})
    ms = MaskSet(source=f"png:{path}")
    files = sorted(p for p in _glob(path, "*/*") if p.suffix.lower() in _IMAGE_EXTS and p.is_file())
    _check_png_dir_level(path, files, image_sizes)
    if not files:
        raise InputError("no <view>/<object>.png masks in this folder", path)
    names = {}
    for p in files:
        names[p] = name_from_label(p.stem, p, "object name (mask file name)")
        view_name(p.parent.name, p.parent, "view name (folder name)")
    _new_labels(labels, sorted(set(names.values())))
    for name in set(names.values()):  # only objects that have mask files
        ms.objects[labels[name]] = name
    _check_names(ms, path)
    for p in files:
        view = p.parent.name
        mask = _read_binary_png(_inside(path, p))
        _check_image(view, mask.shape, image_sizes, p)
        ms.add(view, labels[names[p]], mask, 1.0, source=p)
    return ms


def _check_png_dir_level(path: Path, files: list[Path], image_sizes: dict | None) -> None:
    """A folder one level above the masks (a scene's masks/ holding gt/ and noisy/) would be read as views
    named gt/noisy with "objects" named like the images, and fail only in the fusion ("no mask view
    matches"): refuse it here, naming the folders to pass instead."""
    hint = (" (a generated scene: splattwin.semantics.scene_masks(scene_dir, kind='noisy' or 'gt'))"
            if (path.parent / "scene.json").is_file() else "")
    nested = sorted(d for d in _entries(path) if d.is_dir() and any(
        c.is_dir() and any(f.suffix.lower() in _IMAGE_EXTS for f in _entries(c) if f.is_file())
        for c in _entries(d)))
    if nested:
        raise InputError(f"this folder holds folders of mask folders ({', '.join(d.name for d in nested[:3])}/<view>/...), "
                         f"not <view>/<object>.png masks: pass one of them, e.g. {nested[0]}{hint}", path)
    if image_sizes:
        views = {p.parent.name for p in files}
        stems = {p.stem for p in files}
        if not views & set(image_sizes) and stems & set(image_sizes):
            raise InputError(f"the mask files are named like the images ({', '.join(sorted(stems & set(image_sizes))[:3])}) "
                             f"and the folders ({', '.join(sorted(views)[:3])}) like none: a folder of <view>.png label "
                             f"images per kind? pass that folder itself, not its parent{hint}", path)


def load_label_images(path: Path, objects: dict[str, int] | None = None, image_sizes: dict | None = None) -> MaskSet:
    """`<path>/<view>.png` label images (pixel = label, 0 background) -> MaskSet.

    objects: name -> label. Without it every non-zero value becomes `object_<value>`.
    """
    ms = MaskSet(source=f"labels:{path}")
    files = sorted(p for p in _entries(path) if p.suffix.lower() in _IMAGE_EXTS and p.is_file())
    if objects:
        for name, label in objects.items():
            ms.objects[int(label)] = object_name(name, path)
        _check_names(ms, path)
    for p in files:
        view = view_name(p.stem, p)
        img = read_mask_image(_inside(path, p, "label image"))
        if img.ndim != 2:
            raise InputError(f"label image must be single-channel, got shape {img.shape}", p)
        if img.dtype.kind not in "biu":
            raise InputError(f"label image must hold whole-number labels, got {img.dtype} pixels", p)
        _check_image(view, img.shape, image_sizes, p)
        ms.sizes[view] = img.shape
        ms.size_sources.setdefault(view, str(p))
        values = np.unique(img)
        values = values[values != 0]
        # bounded before a mask is built: each label costs a full-size mask (a 389-byte PNG can hold 32768)
        if values.size > MAX_OBJECTS_PER_VIEW:
            raise InputError(f"label image holds {values.size} distinct labels, more than the limit of "
                             f"{MAX_OBJECTS_PER_VIEW} objects per view (is it a photo or depth map, not labels?)", p)
        present = [int(v) for v in values]
        if present and not (0 < present[0] and present[-1] <= MAX_LABEL_ID):
            raise InputError(f"label image values must lie in [0, {MAX_LABEL_ID}], got {present[0]}..{present[-1]}", p)
        for label in present:
            if objects and label not in ms.objects:
                continue
            ms.add(view, label, img == label, 1.0, source=p)
    return ms


def load_coco(path: Path, objects: dict[str, int] | None = None, image_sizes: dict | None = None) -> MaskSet:
    """COCO JSON (RLE or polygon segmentations) -> MaskSet; views are the image file stems.

    Category names are object names after `name_from_label` ("toy hammer" -> `toy_hammer`; the text
    becomes the object's prompt); their labels are the category ids unless `objects` names them. Every
    image and RLE size is checked before a mask is allocated."""
    data = io.read_json(path)
    ms = MaskSet(source=f"coco:{path}")
    labels = dict(objects or {})
    if not isinstance(data, dict):
        raise InputError("malformed COCO JSON: expected an object with images, annotations, categories", path)
    try:
        cats = data.get("categories", [])
        if not isinstance(cats, list) or len(cats) > MAX_CATEGORIES:
            raise InputError(f"categories must be a list of at most {MAX_CATEGORIES} entries", path)
        cat_name, cat_text = {}, {}
        for c in cats:
            cid = whole_number(c["id"], path, "category id", 0, MAX_ID)
            if cid in cat_name:
                raise InputError(f"category id {cid} appears twice", path)
            cat_name[cid] = name_from_label(c["name"], path, f"category {cid} name")
            cat_text[cat_name[cid]] = " ".join(str(c["name"]).split())
        check_unique(cat_name.values(), path, "category name")
        images = {}
        for im in data["images"]:
            iid = whole_number(im["id"], path, "image id", 0, MAX_ID)
            if iid in images:
                raise InputError(f"image id {iid} appears twice", path)
            file_name = im["file_name"]
            if not isinstance(file_name, str):
                raise InputError(f"image {iid} file_name must be a string, got {short_repr(file_name)}", path)
            view = view_name(Path(file_name).stem, path, f"image {iid} file_name")
            if view in ms.sizes:  # two images whose masks would merge into one view
                raise InputError(f"two images have the view name {view!r} (image {iid}, file_name {file_name!r})",
                                 path)
            W, H = check_pixels(im["width"], im["height"], path, f"image {file_name!r}")
            _check_image(view, (H, W), image_sizes, path)
            images[iid] = (view, H, W, file_name)
            ms.sizes[view] = (H, W)
        # labels: the given objects' (a scene's), else the category id itself, so that every route (segment,
        # fuse, build) numbers the objects alike; a fresh one only where the id is < 1 or already taken
        used = set(labels.values())  # a set: `in labels.values()` per category is quadratic
        for cid, name in sorted(cat_name.items()):
            if name not in labels and 1 <= cid <= MAX_LABEL_ID and cid not in used:
                labels[name] = cid
                used.add(cid)
        _new_labels(labels, sorted(set(cat_name.values())))
        cat_names = set(cat_name.values())
        for name, label in labels.items():
            if name in cat_names:
                ms.objects[label] = name
                if cat_text.get(name) and cat_text[name] != name:
                    ms.prompts[label] = cat_text[name]
        for i, ann in enumerate(data["annotations"]):
            iid = whole_number(ann["image_id"], path, f"annotation {i} image_id", 0, MAX_ID)
            im = images.get(iid)
            if im is None:
                raise InputError(f"annotation {i} refers to unknown image_id {iid}", path)
            view, H, W, file_name = im
            cid = whole_number(ann["category_id"], path, f"annotation {i} category_id", 0, MAX_ID)
            if cid not in cat_name:
                raise InputError(f"annotation {i} refers to unknown category_id {cid}", path)
            score = _score(ann.get("score", 1.0), path, f"annotation {i} score")
            seg = ann["segmentation"]
            if isinstance(seg, dict):
                try:
                    h, w = seg["size"]
                except (KeyError, TypeError, ValueError) as e:
                    raise InputError(f"annotation {i}: malformed RLE (need size [h, w] and counts): {e}", path) from e
                w, h = check_pixels(w, h, path, f"annotation {i} RLE")
                if (h, w) != (H, W):
                    raise InputError(f"annotation {i}: RLE size {w}x{h} differs from its image {file_name} ({W}x{H})",
                                     path)
                try:
                    mask = rle_codec.decode(seg)
                except InputError as e:
                    raise InputError(f"annotation {i}: {e.problem}", path) from None
            elif isinstance(seg, list):
                mask = polygons_to_mask([np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in seg], H, W, path)
            else:
                raise InputError(f"annotation {i}: segmentation must be RLE or polygons", path)
            ms.add(view, labels[cat_name[cid]], mask, score, source=path)
    except InputError as e:
        if e.path is None:
            raise InputError(e.problem, path) from None
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(f"malformed COCO JSON: {e}", path) from e
    return ms


# -- per-instance mask files (BOP and similar) ------------------------------------------------------

INSTANCES_FILE = "instances.json"
_INSTANCE_RE = re.compile(r"^(.+)_([0-9]{1,9})$")  # ASCII digits (\d also takes other scripts' digits)
_SAME_INSTANCE_M = 0.05  # instances of one obj_id closer than this in the world are the same object


def find_bop_scene(path: Path) -> Path | None:
    """The BOP scene folder of a mask path: the scene itself (with scene_gt.json and mask_visib/ or
    mask/), or its mask_visib/ or mask/ folder; None when `path` is neither."""
    from splattwin.capture.bop import MASK_DIRS, SCENE_GT

    path = Path(path)
    if path.is_dir() and (path / SCENE_GT).is_file() and any((path / d).is_dir() for d in MASK_DIRS):
        return path
    if path.is_dir() and path.name in MASK_DIRS and (path.parent / SCENE_GT).is_file():
        return path.parent
    return None


def _bop_instance_keys(gt: dict, T_world_cam: dict[int, np.ndarray] | None, where: Path) -> dict[tuple[int, int], tuple[int, int]]:
    """(image id, instance index) -> (obj_id, n): the n-th distinct object with that obj_id.

    Linear in the instances apart from one vectorised distance per repeated instance to the objects
    of its obj_id found so far (at most MAX_OBJECTS_PER_VIEW instances per image)."""
    from collections import Counter

    keys: dict[tuple[int, int], tuple[int, int]] = {}
    dup_ids = set()
    for im_id, insts in gt.items():
        if len(insts) > MAX_OBJECTS_PER_VIEW:
            raise InputError(f"image {im_id} lists {len(insts)} instances, more than the limit of "
                             f"{MAX_OBJECTS_PER_VIEW} objects per view", where)
        dup_ids.update(oid for oid, k in Counter(g.obj_id for g in insts).items() if k > 1)
    centres: dict[int, np.ndarray] = {}   # obj_id -> [N,3] world positions of its distinct objects
    warned = False
    for im_id in sorted(gt):
        seen: dict[int, np.ndarray] = {}   # obj_id -> bool [N]: objects already given an instance here
        n_here: dict[int, int] = {}
        for g in gt[im_id]:
            if g.obj_id not in dup_ids:
                keys[(im_id, g.index)] = (g.obj_id, 0)
                continue
            if T_world_cam is not None and im_id in T_world_cam:
                p = (T_world_cam[im_id] @ g.T_cam_obj)[:3, 3]
                cs = centres.setdefault(g.obj_id, np.zeros((0, 3)))
                taken = seen.setdefault(g.obj_id, np.zeros(0, bool))
                taken = np.concatenate([taken, np.zeros(len(cs) - len(taken), bool)])
                d = np.linalg.norm(cs - p, axis=1)
                d[taken] = np.inf
                n = int(np.argmin(d)) if d.size and d.min() < _SAME_INSTANCE_M else len(cs)
                if n == len(cs):
                    centres[g.obj_id] = np.vstack([cs, p])
                    taken = np.append(taken, False)
                taken[n] = True
                seen[g.obj_id] = taken
            else:
                if not warned:
                    log.warning("%s: several instances of one obj_id and no camera poses: instances are told apart "
                                "by their order in each image's list", where)
                    warned = True
                n = n_here.get(g.obj_id, 0)
                n_here[g.obj_id] = n + 1
            keys[(im_id, g.index)] = (g.obj_id, n)
    return keys


def load_bop_masks(path: str | Path, objects: dict[str, int] | None = None,
                   image_sizes: dict | None = None) -> MaskSet:
    """A BOP scene's per-instance masks -> MaskSet (layout in the module docstring). Views are the
    image stems (`000012`); instances whose mask file is missing or empty are left out of that view."""
    from splattwin.capture.bop import (MASK_DIRS, SCENE_CAMERA, SCENE_GT, mask_name, names_source, object_names,
                                       read_scene_gt)

    path = Path(path)
    scene = find_bop_scene(path)
    if scene is None:
        raise InputError("not a BOP scene or mask folder (needs scene_gt.json and mask_visib/ or mask/)", path)
    mask_dir = path if path.name in MASK_DIRS and path != scene else next(scene / d for d in MASK_DIRS
                                                                         if (scene / d).is_dir())
    gt_file = scene / SCENE_GT
    gt = read_scene_gt(gt_file)
    T_world_cam = None
    if (scene / SCENE_CAMERA).is_file():
        from splattwin.capture import bop

        try:
            ds = bop.read(scene)
            if ds.has_poses:
                T_world_cam = {int(f.camera.name): f.camera.T_world_cam for f in ds.frames}
        except InputError as e:  # the masks do not need the images; say why poses were not used
            log.info("%s: camera poses not used to tell instances apart (%s)", scene, e)
    keys = _bop_instance_keys(gt, T_world_cam, gt_file)
    base = object_names(scene, sorted({k[0] for k in keys.values()}))
    name_of = {(oid, n): (base[oid] if n == 0 else f"{base[oid]}_{n + 1}")
               for oid, n in sorted(set(keys.values()))}
    for nm in name_of.values():
        object_name(nm, gt_file)
    # a collision left here comes from the names file ("mug" with 2 instances -> "mug_2", also a name there)
    check_unique(name_of.values(), names_source(scene) or gt_file)
    labels = dict(objects or {})
    _new_labels(labels, [name_of[key] for key in sorted(name_of)])
    ms = MaskSet(source=f"bop:{mask_dir}")
    missing = []
    for im_id in sorted(gt):
        view = f"{im_id:06d}"
        for g in gt[im_id]:
            f = mask_dir / mask_name(im_id, g.index)
            if not f.is_file():
                missing.append(f.name)
                continue
            nm = name_of[keys[(im_id, g.index)]]
            _add_instance_png(ms, view, labels[nm], nm, _inside(scene, f), image_sizes)
    if missing:
        log.warning("%s: %d instance mask file(s) listed in %s are missing (e.g. %s)", mask_dir, len(missing),
                    SCENE_GT, ", ".join(missing[:3]))
    if not ms.sizes:
        raise InputError(f"no mask file of {SCENE_GT} exists in {mask_dir.name}/", mask_dir)
    _check_names(ms, gt_file)
    return ms


def _looks_per_instance(path: Path, image_sizes: dict | None) -> bool:
    """Flat files named `<view>_<number>` where the views are known and no file is a view itself."""
    if not image_sizes:
        return False
    stems = [p.stem for p in _entries(path) if p.is_file() and p.suffix.lower() in _IMAGE_EXTS]
    if not stems or any(s in image_sizes for s in stems):
        return False
    return all((m := _INSTANCE_RE.match(s)) is not None and m.group(1) in image_sizes for s in stems)


def load_instance_masks(path: str | Path, objects: dict[str, int] | None = None,
                        image_sizes: dict | None = None) -> MaskSet:
    """`<dir>/<view>_<instance>.png` binary masks -> MaskSet; names from `<dir>/instances.json`
    (`{"<instance>": "name"}`, instance numbers compared as integers) or `instance_<n>`."""
    path = Path(path)
    names: dict[int, str] = {}
    index = path / INSTANCES_FILE
    if index.is_file():
        data = io.read_json(_inside(path, index, INSTANCES_FILE))
        if not isinstance(data, dict):
            raise InputError('expected an object {"<instance number>": "object name", ...}', index)
        for k, v in data.items():
            if ascii_uint(k, 9) is None:
                raise InputError(f"instance key {k!r} must be a whole number (digits 0-9, at most 9)", index)
            if int(k) in names:  # "1" and "01"
                raise InputError(f"instance {int(k)} is named twice (key {k!r} and another with the same number)",
                                 index)
            names[int(k)] = name_from_label(v, index, f"name of instance {k}")
        # two instances of one name would merge into one object (as BOP's object_names.json refuses)
        check_unique(names.values(), index)
    files = sorted(p for p in _entries(path) if p.is_file() and p.suffix.lower() in _IMAGE_EXTS)
    if not files:
        raise InputError("no <view>_<instance>.png mask files in this folder", path)
    parsed = []
    for p in files:
        m = _INSTANCE_RE.match(p.stem)
        if m is None:
            raise InputError("per-instance mask file names must be <view>_<instance number>.png", p)
        view, inst = view_name(m.group(1), p, "view name (file name before _<instance>)"), int(m.group(2))
        if names and inst not in names:
            raise InputError(f"instance {inst} (file {p.name}) has no name in {INSTANCES_FILE}", index)
        parsed.append((p, view, inst))
    name_of = {inst: names.get(inst, f"instance_{inst}") for _, _, inst in parsed}
    check_unique(set(name_of.values()), index if names else path)
    labels = dict(objects or {})
    _new_labels(labels, [name_of[inst] for inst in sorted(name_of)])
    ms = MaskSet(source=f"instances:{path}")
    for p, view, inst in parsed:
        _add_instance_png(ms, view, labels[name_of[inst]], name_of[inst], _inside(path, p), image_sizes)
    _check_names(ms, path)
    return ms



def _add_instance_png(ms: MaskSet, view: str, label: int, name: str, f: Path, image_sizes) -> None:
    """Read one binary instance-mask PNG, check its size against the view's image and the view's other
    masks (naming the file), and add it to `ms` unless it is empty."""
    mask = _read_binary_png(f)
    _check_image(view, mask.shape, image_sizes, f)
    _check_size(ms, view, mask, f)
    ms.sizes.setdefault(view, mask.shape)
    ms.size_sources.setdefault(view, str(f))
    if mask.any():
        ms.add(view, label, mask, 1.0, name=name, source=f)

def save_instance_masks(ms: MaskSet, out_dir: str | Path) -> Path:
    """Write `<out_dir>/<view>_<label:06d>.png` (0/255) and `instances.json` ({label: name})."""
    out_dir = Path(out_dir)
    for view in ms.views:
        for label, m in sorted(ms.masks.get(view, {}).items()):
            io.write_image(child(out_dir, f"{view_name(view)}_{label:06d}.png"), m.astype(np.uint8) * 255)
    io.write_json(out_dir / INSTANCES_FILE, {str(k): object_name(v) for k, v in sorted(ms.objects.items())})
    return out_dir


def save_coco(ms: MaskSet, path: str | Path, compressed: bool = True) -> Path:
    """Write a MaskSet as COCO JSON with RLE segmentations (file_name = `<view>.png`)."""
    images, anns = [], []
    for i, view in enumerate(ms.views, start=1):
        H, W = ms.sizes[view]
        images.append({"id": i, "file_name": f"{view}.png", "height": H, "width": W})
        for label, m in sorted(ms.masks.get(view, {}).items()):
            ys, xs = np.nonzero(m)
            bbox = [0, 0, 0, 0] if xs.size == 0 else [int(xs.min()), int(ys.min()),
                                                      int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]
            anns.append({"id": len(anns) + 1, "image_id": i, "category_id": int(label),
                         "segmentation": rle_codec.encode(m, compressed), "area": int(m.sum()), "bbox": bbox,
                         "iscrowd": 0, "score": ms.scores[view][label]})
    cats = [{"id": int(k), "name": n} for k, n in sorted(ms.objects.items())]
    return io.write_json(path, {"images": images, "annotations": anns, "categories": cats}, indent=None)


def load_polygon_dir(path: Path, objects: dict[str, int] | None = None, object_name: str | None = None,
                     image_sizes: dict | None = None) -> MaskSet:
    """Polygon JSON masks of the paper's published code -> MaskSet (layout in the module docstring)."""
    ms = MaskSet(source=f"polygons:{path}")
    labels = dict(objects or {})
    flat = sorted(_glob(path, "*_mask.json"))
    groups: list[tuple[str | None, list[Path]]] = []
    if flat:
        groups.append((object_name, flat))
    for sub in sorted(p for p in _entries(path) if p.is_dir()):
        files = sorted(_glob(sub, "*_mask.json"))
        if files:
            groups.append((sub.name, files))
    for default_name, files in groups:
        for f in files:
            d = io.read_json(_inside(path, f, "polygon mask file"))
            if not isinstance(d, dict):
                raise InputError("malformed polygon mask JSON: expected an object", f)
            try:
                name = name_from_label(d.get("object") or default_name or path.name, f)
                W, H = check_pixels(d["image_width"], d["image_height"], f, "image_width x image_height")
                polys = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in d["segmentation_polygons"] if len(p)]
                image_file = d.get("image_filename") or f.name[: -len("_mask.json")]
                if not isinstance(image_file, str):
                    raise InputError(f"image_filename must be a string, got {short_repr(image_file)}", f)
                view = view_name(Path(image_file).stem, f, "image_filename")
                score = _score(d.get("score", 1.0), f, "score")
            except (KeyError, TypeError, ValueError) as e:
                raise InputError(f"malformed polygon mask JSON: {e}", f) from e
            _check_image(view, (H, W), image_sizes, f)
            _new_labels(labels, [name])
            ms.objects[labels[name]] = name
            ms.add(view, labels[name], polygons_to_mask(polys, H, W, f), score, source=f)
    _check_names(ms, path)
    return ms


def save_polygon_dir(ms: MaskSet, out_dir: str | Path) -> Path:
    """Write the paper-code polygon layout: `<out_dir>/<object>/<view>_mask.json` (OpenCV contours)."""
    import cv2

    out_dir = Path(out_dir)
    for view in ms.views:
        H, W = ms.sizes[view]
        for label, m in ms.masks.get(view, {}).items():
            contours, _ = cv2.findContours(m.astype(np.uint8) * 255, cv2.RETR_TREE, cv2.CHAIN_APPROX_SIMPLE)
            polys = [c.reshape(-1, 2).tolist() for c in contours if len(c)]
            folder = child(out_dir, safe_name(object_name(ms.objects[label])))
            io.write_json(child(folder, f"{view_name(view)}_mask.json"),
                          {"image_filename": f"{view}.png", "image_height": H, "image_width": W,
                           "input_points": [], "input_labels": [], "segmentation_polygons": polys,
                           "object": ms.objects[label], "score": ms.scores[view][label]})
    return out_dir


def polygons_to_mask(polygons: list[np.ndarray], height: int, width: int, where: str | Path | None = None) -> np.ndarray:
    """Fill polygons ([M,2] pixel x,y each) into a bool [H,W] mask with OpenCV (as the published code)."""
    import cv2

    width, height = check_pixels(width, height, where, "mask")
    for p in polygons:
        if not np.all(np.isfinite(p)) or np.abs(p).max(initial=0) > 1e6:
            raise InputError("polygon coordinates must be finite pixel positions", where)
    img = np.zeros((height, width), dtype=np.uint8)
    pts = [np.round(p).astype(np.int32).reshape(-1, 1, 2) for p in polygons if len(p) >= 1]
    if pts:
        cv2.fillPoly(img, pts, 255)
    return img > 0


def scene_masks(scene_dir: str | Path, kind: str = "noisy") -> MaskSet:
    """The embedded scene's masks: kind "noisy" (`masks/noisy/<view>/<object>.png`) or "gt" (label images).

    Object names, labels and prompts come from `scene.json` (the table is background).
    """
    scene_dir = Path(scene_dir)
    objs = scene_objects(scene_dir)
    sub = scene_dir / "masks" / kind
    if not sub.is_dir():
        raise InputError(f"no {kind} masks in the scene folder", sub)
    ms = load_png_dir(sub, objs) if kind != "gt" else load_label_images(sub, objs)
    # views where an object was not found still count as views (sizes from the images)
    from splattwin.limits import image_size

    for img in sorted((scene_dir / "images").glob("*.png")):
        if img.stem not in ms.sizes and (kind == "gt" or (sub / img.stem).is_dir()):
            w, h = image_size(img)
            ms.sizes[img.stem] = (h, w)
    meta = io.read_json(scene_dir / "scene.json")
    for o in meta.get("objects", []) if isinstance(meta, dict) else []:
        prompt = o.get("prompt") if isinstance(o, dict) else None
        if prompt is not None and not isinstance(prompt, str):   # text only: it names the object downstream
            raise InputError(f"an object's prompt must be text, got {type(prompt).__name__}", scene_dir / "scene.json")
        if prompt and isinstance(o.get("label"), int) and o["label"] in ms.objects:
            ms.prompts[o["label"]] = prompt
    ms.objects = {k: v for k, v in ms.objects.items() if v in objs}
    ms.source = f"scene:{kind}:{scene_dir}"
    return ms


def scene_objects(scene_dir: str | Path) -> dict[str, int]:
    """name -> label of the embedded scene's objects (from scene.json; label 0 / "table" excluded)."""
    where = Path(scene_dir) / "scene.json"
    meta = io.read_json(where)
    try:
        # labels held to `whole_number` as `lift._scene_prompts` holds them: the two readers of scene.json agree
        out = {object_name(o["name"], where): label for o in meta["objects"]
               if (label := whole_number(o["label"], where, f"scene.json label of object {short_repr(o['name'])}",
                                   0, MAX_LABEL_ID)) > 0 and o["name"] != "table"}
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(f"malformed scene.json objects: {e}", where) from e
    check_unique(out, where)
    return out


# -- helpers ----------------------------------------------------------------------------------

def safe_name(name: str) -> str:
    """`name` as a file-name stem: runs of characters other than letters, digits, _ . - become one _;
    "object" when nothing is left."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "object"



def whole_number(v, where, what: str, lo: int, hi: int) -> int:
    """`v` if it is a JSON integer (not a bool, 1.7 or 1e400) in [lo, hi], else InputError."""
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(f"{what} must be a whole number, got {short_repr(v)}", where)
    if not lo <= v <= hi:
        raise InputError(f"{what} {short_repr(v)} is outside [{lo}, {hi}]", where)
    return v


def _score(v, where, what: str) -> float:
    """A mask score: a number in [0, 1] (NaN, inf and strings refused)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 1:  # NaN fails 0 <= v
        raise InputError(f"{what} must be a number in [0, 1], got {short_repr(v)}", where)
    return float(v)


def _new_labels(labels: dict[str, int], names) -> None:
    """Give each of `names` missing from `labels` the next label above the highest, in order (a running
    maximum: max() per name is quadratic in the number of names)."""
    top = max(labels.values(), default=0)
    for n in names:
        if n not in labels:
            top += 1
            labels[n] = top


def _inside(root: Path, f: Path, what: str = "mask file") -> Path:
    """`f`, found by listing a folder under `root`, unless it is a symbolic link leading out of `root`:
    received masks must not pull in files from elsewhere (as paths named in an index are confined)."""
    return confined(root, f.relative_to(root).as_posix(), f, what)


def read_mask_image(path: Path) -> np.ndarray:
    """Decoded mask / label image; its header size is checked first (`splattwin.limits`)."""
    return read_image_array(path, what="mask image")


def _read_binary_png(path: Path) -> np.ndarray:
    img = read_mask_image(path)
    if img.ndim == 3:  # RGB(A) mask: any non-zero colour channel is inside
        img = img[..., :3].max(axis=2)
    return img > 0


def _check_size(ms: MaskSet, view: str, mask: np.ndarray, path: Path) -> None:
    hw = ms.sizes.get(view)
    if hw is not None and tuple(hw) != mask.shape:
        first = ms.size_sources.get(view)
        # name the file that set the view's size: it may be the wrong one
        by = f" (the size of {first})" if first and first != str(path) else ""
        raise InputError(f"mask is {mask.shape[1]}x{mask.shape[0]} but view {view!r} is {hw[1]}x{hw[0]}{by}", path)
