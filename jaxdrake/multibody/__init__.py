"""Rigid-body systems: URDF -> kinematic tree, Featherstone's algorithms in JAX."""

from ._actuators import FixedTendons, JointActuators
from ._algorithms import (aba, bias_forces, fused_kernels, BodyMotion, body_motion, body_poses, external_forces, configuration_derivative, frame_jacobian,
                          frame_pose, gravity_forces, kinetic_energy, mass_matrix,
                          potential_energy, rnea)
from ._contact import CollisionGeometry, ContactMaterial, ContactModel, ContactResults
from ._files import parse_xml, resolve_model_file
from ._joints import JointType
from ._mjcf import MJCFError, check_model_files, mjcf_render_model, tree_from_mjcf
from ._plant import CouplerConstraint, LoopConstraint, RigidBodySystem
from ._spatial import rpy
from ._tree import KinematicTree, URDFError, tree_from_pinocchio, tree_from_urdf, urdf_mimic_joints

__all__ = ["CollisionGeometry", "ContactMaterial", "ContactModel", "ContactResults", "CouplerConstraint", "FixedTendons", "JointActuators", "JointType", "KinematicTree", "LoopConstraint", "MJCFError", "RigidBodySystem", "URDFError", "aba", "bias_forces", "BodyMotion", "body_motion", "body_poses", "check_model_files", "external_forces", "fused_kernels",
           "configuration_derivative", "frame_jacobian", "frame_pose", "gravity_forces",
           "kinetic_energy", "mass_matrix", "mjcf_render_model", "parse_xml", "potential_energy", "resolve_model_file", "rnea", "rpy", "tree_from_mjcf", "tree_from_pinocchio", "tree_from_urdf", "urdf_mimic_joints"]
