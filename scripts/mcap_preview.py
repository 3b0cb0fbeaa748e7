"""Draw a poses log's `foxglove.ImageAnnotations` over the drive log's camera images, as an image
panel shows them, into one PNG contact sheet (docs/ROS.md, "Looking at the output").

    python scripts/mcap_preview.py --drive drive.mcap --poses poses.mcap --out preview.png [--frames 4]

Both logs are read with the official `mcap` reader: the images through `mcap-ros2-support`, the
annotations through Foxglove's published protobuf classes. An annotation is drawn on the image of
its camera topic whose stamp equals the annotation's.
"""

import argparse
import io

from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from PIL import Image, ImageDraw

PREFIX = "/posefuse/annotations"


def stamp(ts) -> int:
    return ts.seconds * 1_000_000_000 + ts.nanos


def rgba(c) -> tuple[int, int, int, int]:
    return tuple(round(255 * v) for v in (c.r, c.g, c.b, c.a))


def annotated(poses_path: str) -> dict[tuple[str, int], ImageAnnotations]:
    out = {}
    with open(poses_path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if not channel.topic.startswith(PREFIX):
                continue
            a = ImageAnnotations.FromString(message.data)
            if a.circles:
                out[(channel.topic[len(PREFIX) :], stamp(a.circles[0].timestamp))] = a
    return out


def draw(img: Image.Image, a: ImageAnnotations) -> None:
    d = ImageDraw.Draw(img)
    for p in a.points:
        if p.type == PointsAnnotation.LINE_LIST:
            for i in range(0, len(p.points) - 1, 2):
                q, r = p.points[i], p.points[i + 1]
                d.line([(q.x, q.y), (r.x, r.y)], fill=rgba(p.outline_color), width=max(1, round(p.thickness)))
    for c in a.circles:
        r = c.diameter / 2
        box = [c.position.x - r, c.position.y - r, c.position.x + r, c.position.y + r]
        d.ellipse(box, fill=rgba(c.fill_color), outline=rgba(c.outline_color))


def around(a: ImageAnnotations, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """The annotated persons with a margin, as a crop box inside the image."""
    xs = [c.position.x for c in a.circles]
    ys = [c.position.y for c in a.circles]
    h = max(max(ys) - min(ys), 40) * 1.6
    cx, cy = (max(xs) + min(xs)) / 2, (max(ys) + min(ys)) / 2
    w = max(max(xs) - min(xs) + h * 0.4, h * 0.75)
    box = (cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2)
    return (max(0, round(box[0])), max(0, round(box[1])), min(size[0], round(box[2])), min(size[1], round(box[3])))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drive", required=True)
    ap.add_argument("--poses", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--frames", type=int, default=4, help="images with annotations to draw")
    ap.add_argument("--height", type=int, default=360, help="height of each tile, pixels")
    a = ap.parse_args()

    wanted = annotated(a.poses)
    tiles = []
    with open(a.drive, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _, msg in reader.iter_decoded_messages():
            if schema.name != "sensor_msgs/msg/CompressedImage":
                continue
            ann = wanted.get((channel.topic, msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec))
            if ann is None:
                continue
            img = Image.open(io.BytesIO(bytes(msg.data))).convert("RGB")
            draw(img, ann)
            img = img.crop(around(ann, img.size))
            img = img.resize((round(img.width * a.height / img.height), a.height))
            tiles.append(img)
            if len(tiles) == a.frames:
                break
    if not tiles:
        raise SystemExit("no image of the drive has annotations in the poses log")
    sheet = Image.new("RGB", (sum(t.width for t in tiles), max(t.height for t in tiles)))
    x = 0
    for t in tiles:
        sheet.paste(t, (x, 0))
        x += t.width
    # 256 colours keep the sheet small enough to commit beside the docs
    sheet.quantize(colors=256).save(a.out, optimize=True)
    print(f"{a.out}: {len(tiles)} images")


if __name__ == "__main__":
    main()
