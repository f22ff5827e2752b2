"""Hand-made Gazebo SDF worlds for the converter's tests (mapex.worlds.gazebo)."""

from __future__ import annotations

from pathlib import Path


def box_link(name: str, pose: str, size: str, collision_pose: str = "0 0 1 0 0 0") -> str:
    """A link holding one collision box (`size` "x y z", poses "x y z roll pitch yaw")."""
    return f"""
    <link name="{name}"><pose>{pose}</pose>
      <collision name="{name}_c"><pose>{collision_pose}</pose>
        <geometry><box><size>{size}</size></box></geometry></collision>
      <visual name="{name}_v"><geometry><box><size>{size}</size></box></geometry></visual>
    </link>"""


def model(name: str, pose: str, links: str, static: bool = True, extra: str = "") -> str:
    """A model of `links` at `pose`."""
    return f"""
  <model name="{name}"><static>{int(static)}</static><pose>{pose}</pose>{links}{extra}
  </model>"""


def world(*models: str, state: str = "", include: str = "") -> str:
    """An SDF world with a ground plane and `models`."""
    ground = """
  <model name="ground_plane"><static>1</static><link name="link"><collision name="c">
    <geometry><plane><normal>0 0 1</normal><size>100 100</size></plane></geometry>
  </collision></link></model>"""
    body = f"{ground}{''.join(models)}{include}{state}"
    return f'<sdf version="1.6"><world name="default">{body}</world></sdf>'


def room_links(width_m: float, depth_m: float, door_m: float = 1.0) -> str:
    """Four 0.1 m walls around a `width_m` x `depth_m` room centred on the origin, with a
    door of `door_m` in the middle of its bottom wall (boxes centred on their links)."""
    w, d, t = width_m, depth_m, 0.1
    side = (w - door_m) / 2
    return "".join(
        [
            box_link("top", f"0 {d / 2} 0 0 0 0", f"{w + t} {t} 2"),
            box_link("left", f"{-w / 2} 0 0 0 0 0", f"{t} {d + t} 2"),
            box_link("right", f"{w / 2} 0 0 0 0 0", f"{t} {d + t} 2"),
            box_link("bottom_a", f"{-w / 2 + side / 2} {-d / 2} 0 0 0 0", f"{side} {t} 2"),
            box_link("bottom_b", f"{w / 2 - side / 2} {-d / 2} 0 0 0 0", f"{side} {t} 2"),
        ]
    )


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path
