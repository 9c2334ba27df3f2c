"""Joint roles (jitdyn.roles): inferred from common joint names, declared by tags, refused with one
line naming the tag when a tag is wrong."""

from __future__ import annotations

import mujoco
import pytest

from jitdyn.errors import InvalidArgument
from jitdyn.registry.info import describe_model
from jitdyn.roles import joint_roles


def _joints(mjcf_joints: str) -> tuple[object, ...]:
    """The joints of a chain of bodies, one hinge or slide each, as the registry describes them."""
    bodies, close = "", ""
    for line in mjcf_joints.strip().splitlines():
        bodies += f'<body pos="0 0 -0.1">{line}<geom size="0.05" mass="1"/>'
        close += "</body>"
    model = mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{bodies}{close}</worldbody></mujoco>")
    return describe_model(model).joints


OPENSIM_LEG = """
<joint name="hip_flexion_r" type="hinge" axis="0 0 1" limited="true" range="-30 120"/>
<joint name="hip_adduction_r" type="hinge" axis="1 0 0" limited="true" range="-50 30"/>
<joint name="knee_angle_r" type="hinge" axis="0 0 1" limited="true" range="-120 10"/>
<joint name="knee_angle_translation_r" type="slide" axis="1 0 0"/>
<joint name="ankle_angle_r" type="hinge" axis="0 0 1" limited="true" range="-40 30"/>
<joint name="subtalar_angle_r" type="hinge" axis="1 0 0"/>
"""


def test_roles_are_inferred_from_common_names_with_their_signs_and_said_so() -> None:
    roles = joint_roles(_joints(OPENSIM_LEG), ())
    assert [(r.joint, r.role, r.dof) for r in roles] == [
        ("hip_flexion_r", "hip_flexion_r", 0),
        # The knee's larger excursion, -120 degrees, is flexion: + is extension.
        ("knee_angle_r", "knee_extension_r", 2),
        # The ankle's larger excursion, -40, is plantarflexion: + is dorsiflexion.
        ("ankle_angle_r", "ankle_dorsiflexion_r", 4),
    ]
    assert [r.source for r in roles] == [
        "inferred from its name",
        "inferred from its name, its sign from its range",
        "inferred from its name, its sign from its range",
    ]
    assert all(r.inferred for r in roles)


def test_two_joints_claiming_one_role_get_none_and_unnamed_joints_none() -> None:
    roles = joint_roles(
        _joints('<joint name="knee_r" type="hinge"/>\n<joint name="knee_bend_r" type="hinge"/>'), ()
    )
    assert roles == ()
    assert joint_roles(_joints('<joint name="a" type="hinge"/>\n<joint name="b" type="hinge"/>'), ()) == ()


def test_declared_roles_replace_what_would_be_inferred() -> None:
    tags = ("lab", "role.knee_flexion_l.knee_angle_r", "role.none.hip_flexion_r")
    roles = joint_roles(_joints(OPENSIM_LEG), tags)
    assert [(r.joint, r.role, r.sign, r.source) for r in roles] == [
        ("knee_angle_r", "knee_flexion_l", 1.0, "declared")
    ]


@pytest.mark.parametrize(
    ("tag", "message"),
    [
        (
            "role.knee_flexion_r.no_such_joint",
            "tag 'role.knee_flexion_r.no_such_joint': the model has no joint 'no_such_joint'",
        ),
        (
            "role.elbow_flexion.knee_angle_r",
            "tag 'role.elbow_flexion.knee_angle_r': no role 'elbow_flexion'; a role is one of",
        ),
        ("role.knee_flexion_r.knee_angle_translation_r", "is a slide, a role needs a hinge"),
    ],
)
def test_a_wrong_role_tag_is_refused_naming_it(tag: str, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message.replace("(", r"\(").replace(")", r"\)")) as raised:
        joint_roles(_joints(OPENSIM_LEG), (tag,))
    assert "\n" not in str(raised.value)


def test_a_joint_declared_twice_is_refused() -> None:
    tags = ("role.knee_flexion_r.knee_angle_r", "role.knee_extension_r.knee_angle_r")
    with pytest.raises(InvalidArgument, match="joint 'knee_angle_r' has a role already"):
        joint_roles(_joints(OPENSIM_LEG), tags)
