"""SynthGrasp: the built-in procedural whole-body grasp dataset (DESIGN §3, deviation 4).

Sequences are written in GRAB's exact file format and folder layout (``grab/s<k>/...npz``
plus ``tools/``), so the GRAB reader loads them unchanged. Modules, in the order the data
flows: ``subjects`` (ten open-skeleton bodies), ``scene`` (a subject at a table),
``grasp`` (a hand closing on an analytic object surface), ``hand_placement`` (where and how
a hand takes hold), ``plan`` (keyframe tracks, grasp/release episodes), ``intents`` (lift,
pass, offhand, inspect, drink, pour), ``ik`` (torso/arm/head kinematics), ``motion``
(plan -> per-frame poses, attached object, contact codes), ``generate`` (the dataset).
"""

from .generate import generate_dataset

__all__ = ["generate_dataset"]
