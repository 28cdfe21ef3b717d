// HumanoidRig.cs: a Unity Humanoid avatar as the retargeter's host skeleton, in plain C#
// (no UnityEngine, so it is compiled and tested under mono: bindings/unity/Tests~/Test.cs).
// ComGraspAnimator.cs feeds it the avatar's bones (Animator.GetBoneTransform) and applies
// the poses it gets back.
using System;
using System.Collections.Generic;

namespace ComGrasp
{
    /// <summary>The humanoid bones, with the names and values of UnityEngine.HumanBodyBones
    /// (in Unity: <c>(HumanBodyBones)(int)bone</c>). The names are the ones the engine's
    /// ready Unity map uses (<see cref="CgBuiltinMap.UnityHumanoid"/>).</summary>
    public enum HumanBone
    {
        Hips = 0, LeftUpperLeg = 1, RightUpperLeg = 2, LeftLowerLeg = 3, RightLowerLeg = 4,
        LeftFoot = 5, RightFoot = 6, Spine = 7, Chest = 8, Neck = 9, Head = 10,
        LeftShoulder = 11, RightShoulder = 12, LeftUpperArm = 13, RightUpperArm = 14,
        LeftLowerArm = 15, RightLowerArm = 16, LeftHand = 17, RightHand = 18,
        LeftToes = 19, RightToes = 20, LeftEye = 21, RightEye = 22, Jaw = 23,
        LeftThumbProximal = 24, LeftThumbIntermediate = 25, LeftThumbDistal = 26,
        LeftIndexProximal = 27, LeftIndexIntermediate = 28, LeftIndexDistal = 29,
        LeftMiddleProximal = 30, LeftMiddleIntermediate = 31, LeftMiddleDistal = 32,
        LeftRingProximal = 33, LeftRingIntermediate = 34, LeftRingDistal = 35,
        LeftLittleProximal = 36, LeftLittleIntermediate = 37, LeftLittleDistal = 38,
        RightThumbProximal = 39, RightThumbIntermediate = 40, RightThumbDistal = 41,
        RightIndexProximal = 42, RightIndexIntermediate = 43, RightIndexDistal = 44,
        RightMiddleProximal = 45, RightMiddleIntermediate = 46, RightMiddleDistal = 47,
        RightRingProximal = 48, RightRingIntermediate = 49, RightRingDistal = 50,
        RightLittleProximal = 51, RightLittleIntermediate = 52, RightLittleDistal = 53,
        UpperChest = 54,
    }

    /// <summary>One bone of an avatar at rest: its pose in the character's space (relative to
    /// the character's root transform), in the engine's coordinate system (Unity: metres,
    /// y up, left-handed), rotation as (x, y, z, w).</summary>
    public struct HumanoidBoneRest
    {
        public HumanBone Bone;
        public float[] Position;
        public float[] Rotation;
    }

    /// <summary>A Humanoid avatar as a host skeleton for <see cref="ComGraspRetargeter"/> with
    /// the ready Unity map: bones named as HumanBodyBones, each parented to its nearest present
    /// humanoid ancestor (so an avatar without UpperChest or shoulders works), rest poses
    /// relative to that parent. Bones are ordered parents first: apply the poses in order.</summary>
    public sealed class HumanoidRig
    {
        /// <summary>The humanoid parent of each bone (Unity's human hierarchy); Hips has none.</summary>
        static readonly Dictionary<HumanBone, HumanBone> HumanParent = BuildParents();

        /// <summary>The bones, in retargeter order (parents first).</summary>
        public HumanBone[] Bones { get; private set; }

        /// <summary>The host skeleton to create the retargeter with.</summary>
        public ComGraspBone[] HostBones { get; private set; }

        readonly Dictionary<HumanBone, int> index = new Dictionary<HumanBone, int>();

        /// <summary>From the avatar's bones at rest (any order; Hips required, each bone once,
        /// rotations of unit length). Throws ArgumentException otherwise.</summary>
        public HumanoidRig(IList<HumanoidBoneRest> rest)
        {
            var byBone = new Dictionary<HumanBone, HumanoidBoneRest>();
            foreach (var b in rest)
            {
                if (!Enum.IsDefined(typeof(HumanBone), b.Bone))
                    throw new ArgumentException("unknown humanoid bone " + (int)b.Bone);
                if (byBone.ContainsKey(b.Bone))
                    throw new ArgumentException("humanoid bone " + b.Bone + " given twice");
                if (b.Position == null || b.Position.Length != 3 || b.Rotation == null || b.Rotation.Length != 4)
                    throw new ArgumentException(b.Bone + ": rest position needs 3 values and rotation 4");
                float n = Quat.Norm(b.Rotation);
                if (!(Math.Abs(n - 1f) < 1e-3f))
                    throw new ArgumentException(b.Bone + ": rest rotation is not of unit length (" + n + ")");
                byBone[b.Bone] = b;
            }
            if (!byBone.ContainsKey(HumanBone.Hips))
                throw new ArgumentException("a humanoid needs its Hips bone");

            // Parents first: a bone's depth in the human hierarchy orders it after its parent.
            var bones = new List<HumanBone>(byBone.Keys);
            bones.Sort((a, b) => Depth(a) != Depth(b) ? Depth(a).CompareTo(Depth(b)) : ((int)a).CompareTo((int)b));
            Bones = bones.ToArray();
            for (int i = 0; i < Bones.Length; i++) index[Bones[i]] = i;

            HostBones = new ComGraspBone[Bones.Length];
            for (int i = 0; i < Bones.Length; i++)
            {
                HumanoidBoneRest b = byBone[Bones[i]];
                HumanBone? p = PresentParent(Bones[i], byBone);
                float[] t, r;
                if (p.HasValue)
                {
                    HumanoidBoneRest pr = byBone[p.Value];
                    float[] inv = Quat.Conjugate(pr.Rotation);
                    t = Quat.Rotate(inv, new[] { b.Position[0] - pr.Position[0], b.Position[1] - pr.Position[1], b.Position[2] - pr.Position[2] });
                    r = Quat.Normalize(Quat.Mul(inv, b.Rotation));
                }
                else
                {
                    t = (float[])b.Position.Clone();
                    r = Quat.Normalize(b.Rotation);
                }
                HostBones[i] = new ComGraspBone
                {
                    Name = Bones[i].ToString(),
                    Parent = p.HasValue ? index[p.Value] : -1,
                    RestTranslation = t,
                    RestRotation = r,
                };
            }
        }

        /// <summary>The bone's index in <see cref="Bones"/> (and in the pose buffer), or -1.</summary>
        public int IndexOf(HumanBone bone)
        {
            int i;
            return index.TryGetValue(bone, out i) ? i : -1;
        }

        /// <summary>A pose buffer for <see cref="ComGraspRetargeter.Retarget"/>: allocate once,
        /// reuse every frame.</summary>
        public CgBonePose[] NewPoseBuffer() { return new CgBonePose[Bones.Length]; }

        /// <summary>A bone name as a HumanBone (HumanBodyBones names, e.g. "LeftHand"), or null.</summary>
        public static HumanBone? Parse(string name)
        {
            HumanBone b;
            if (name != null && Enum.TryParse(name, false, out b) && Enum.IsDefined(typeof(HumanBone), b) && b.ToString() == name)
                return b;
            return null;
        }

        /// <summary>The humanoid parent of a bone in Unity's human hierarchy (null for Hips).</summary>
        public static HumanBone? ParentOf(HumanBone bone)
        {
            HumanBone p;
            return HumanParent.TryGetValue(bone, out p) ? p : (HumanBone?)null;
        }

        static HumanBone? PresentParent(HumanBone bone, Dictionary<HumanBone, HumanoidBoneRest> present)
        {
            HumanBone? p = ParentOf(bone);
            while (p.HasValue && !present.ContainsKey(p.Value)) p = ParentOf(p.Value);
            return p;
        }

        static int Depth(HumanBone bone)
        {
            int d = 0;
            for (HumanBone? p = ParentOf(bone); p.HasValue; p = ParentOf(p.Value)) d++;
            return d;
        }

        static Dictionary<HumanBone, HumanBone> BuildParents()
        {
            var p = new Dictionary<HumanBone, HumanBone>
            {
                { HumanBone.Spine, HumanBone.Hips }, { HumanBone.Chest, HumanBone.Spine },
                { HumanBone.UpperChest, HumanBone.Chest }, { HumanBone.Neck, HumanBone.UpperChest },
                { HumanBone.Head, HumanBone.Neck }, { HumanBone.Jaw, HumanBone.Head },
                { HumanBone.LeftEye, HumanBone.Head }, { HumanBone.RightEye, HumanBone.Head },
            };
            foreach (string side in new[] { "Left", "Right" })
            {
                Action<string, string> add = (child, parent) =>
                    p[(HumanBone)Enum.Parse(typeof(HumanBone), side + child)] = parent == "UpperChest" || parent == "Hips"
                        ? (HumanBone)Enum.Parse(typeof(HumanBone), parent)
                        : (HumanBone)Enum.Parse(typeof(HumanBone), side + parent);
                add("UpperLeg", "Hips");
                add("LowerLeg", "UpperLeg");
                add("Foot", "LowerLeg");
                add("Toes", "Foot");
                add("Shoulder", "UpperChest");
                add("UpperArm", "Shoulder");
                add("LowerArm", "UpperArm");
                add("Hand", "LowerArm");
                foreach (string finger in new[] { "Thumb", "Index", "Middle", "Ring", "Little" })
                {
                    add(finger + "Proximal", "Hand");
                    add(finger + "Intermediate", finger + "Proximal");
                    add(finger + "Distal", finger + "Intermediate");
                }
            }
            return p;
        }
    }

    /// <summary>Quaternion helpers on (x, y, z, w) arrays (plain C#: no UnityEngine here).</summary>
    static class Quat
    {
        public static float Norm(float[] q) { return (float)Math.Sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]); }

        public static float[] Normalize(float[] q)
        {
            float n = Norm(q);
            return new[] { q[0] / n, q[1] / n, q[2] / n, q[3] / n };
        }

        public static float[] Conjugate(float[] q) { return new[] { -q[0], -q[1], -q[2], q[3] }; }

        public static float[] Mul(float[] a, float[] b)
        {
            return new[]
            {
                a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
                a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
                a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
                a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
            };
        }

        /// <summary>v rotated by the unit quaternion q.</summary>
        public static float[] Rotate(float[] q, float[] v)
        {
            float[] r = Mul(Mul(q, new[] { v[0], v[1], v[2], 0f }), Conjugate(q));
            return new[] { r[0], r[1], r[2] };
        }
    }
}
