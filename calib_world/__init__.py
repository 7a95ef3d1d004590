"""An independent simulated world: physical robots with hidden mechanical causes, measured by a laser tracker.

It shares NO code with the diagnosis (calib_core.effects, diagnosis, identify, kinematics, statics, twin,
solve): its kinematics, statics, causes and noise model are written here from the mechanics, so that a
diagnosis tested on it proves it finds physics, not its own dictionary entries.  It only reads the
nominal model (calib_core.model) and returns the contract's Measurements (calib_core.io).

    world = World(parse_model(spray7()), seed=1)
    info = hide(world, "telescopic_bending", 5.0, rng)       # sized 5x the noise, unabsorbable part
    meas = world.measure(info["q"])                            # Measurements; truth in world.last.truth
"""
from .campaign import Campaign, Truth, World, sample_joints
from .mechanics import (BaseTilt, CableForce, Cantilever, Cause, ElasticBearings, EncoderScale, GearError, GearPlay,
                        GrossOutliers, JointSpring, JointSprings, LinkGrowth, RailStraightness, ReHoming, TargetStep,
                        TelescopicSag, ThermalGrowth, TiltedBase)
from .robot import PhysicalRobot, Pose
from .scenarios import EXPECTED, EXPECTED_34, KINDS, MECHANISMS_34, hide, null_world

__all__ = [
    "World", "Campaign", "Truth", "sample_joints", "PhysicalRobot", "Pose", "hide", "null_world", "EXPECTED",
    "KINDS", "EXPECTED_34", "MECHANISMS_34", "Cause", "JointSpring", "GearPlay", "GearError", "EncoderScale",
    "RailStraightness", "Cantilever", "BaseTilt", "ElasticBearings", "ReHoming", "ThermalGrowth", "CableForce", "GrossOutliers",
    "JointSprings", "LinkGrowth", "TargetStep", "TiltedBase", "TelescopicSag",
]
