// ComGraspAnimator.cs: drives a Humanoid avatar's bones and the grasped object from the
// engine's retargeted frames. The only file of the package that touches UnityEngine; the rest
// (Comgrasp.cs, HumanoidRig.cs) is plain C# tested under mono. tests/csharp_binding.rs also
// compiles this file against a stub of the UnityEngine types it uses (tests/host_support/
// UnityEngineStub.cs), which checks our code, not Unity's API: it has not been compiled
// against a real Unity install here.
#if UNITY_5_3_OR_NEWER
using System.Collections.Generic;
using UnityEngine;

namespace ComGrasp
{
    /// <summary>Put it on a character with a Humanoid Animator, standing in its rest pose
    /// (T- or A-pose) when the scene starts, and optionally give it the object to grasp.
    /// <see cref="Play"/> starts a motion for <see cref="prompt"/>; frames play at the model's
    /// frame rate while generation continues; <see cref="Cancel"/> stops it. With
    /// <see cref="chain"/>, the next Play continues from where the last motion ended (pose,
    /// place and object).</summary>
    [AddComponentMenu("ComGrasp/ComGrasp Animator")]
    public sealed class ComGraspAnimator : MonoBehaviour
    {
        [Tooltip("What the character does.")]
        public string prompt = "A woman drinks from the mug";
        [Tooltip("The character's Animator (Humanoid); empty: the one on this GameObject.")]
        public Animator animator;
        [Tooltip("The object to grasp (its pivot at the object's origin). Its position anchors the motion; it must be within reach (0.8 m horizontally, 0.3-1.6 m above the character's feet). Optional.")]
        public Transform graspedObject;
        [Tooltip("A model bundle directory; empty: the default model built into the library.")]
        public string bundlePath = "";
        [Tooltip("Sampler seed; 0: the bundle's.")]
        public ulong seed;
        [Tooltip("Start a motion in Start().")]
        public bool playOnStart = true;
        [Tooltip("Play continues from the end of the previous motion.")]
        public bool chain = true;

        /// <summary>True while a motion plays.</summary>
        public bool Playing { get { return stream != null; } }

        ComGraspEngine engine;
        ComGraspRetargeter retargeter;
        HumanoidRig rig;
        Transform[] bones;
        CgBonePose[] poses;
        ComGraspStream stream;
        CgFrame frame; // the newest frame shown
        CgFrame next;  // polled, waiting for its time while `held`
        bool held;
        double clock;
        ulong lastEnded;

        void Awake()
        {
            if (animator == null) animator = GetComponent<Animator>();
            if (animator == null || !animator.isHuman)
            {
                Debug.LogError("ComGraspAnimator needs a Humanoid Animator", this);
                enabled = false;
                return;
            }
            engine = new ComGraspEngine(new ComGraspEngineOptions
            {
                BundlePath = string.IsNullOrEmpty(bundlePath) ? null : bundlePath,
                Coordinates = CgCoordinateSystem.Unity,
            });
            // The avatar's rest pose, as it stands now, in the character's space.
            var rest = new List<HumanoidBoneRest>();
            var found = new Dictionary<HumanBone, Transform>();
            Quaternion toLocal = Quaternion.Inverse(transform.rotation);
            for (int b = 0; b < (int)HumanBodyBones.LastBone; b++)
            {
                Transform t = animator.GetBoneTransform((HumanBodyBones)b);
                if (t == null) continue;
                Vector3 p = transform.InverseTransformPoint(t.position);
                Quaternion q = toLocal * t.rotation;
                found[(HumanBone)b] = t;
                rest.Add(new HumanoidBoneRest
                {
                    Bone = (HumanBone)b,
                    Position = new[] { p.x, p.y, p.z },
                    Rotation = new[] { q.x, q.y, q.z, q.w },
                });
            }
            rig = new HumanoidRig(rest);
            bones = new Transform[rig.Bones.Length];
            for (int i = 0; i < bones.Length; i++) bones[i] = found[rig.Bones[i]];
            retargeter = new ComGraspRetargeter(engine, rig.HostBones, CgBuiltinMap.UnityHumanoid);
            poses = rig.NewPoseBuffer();
        }

        void Start()
        {
            if (playOnStart && enabled) Play();
        }

        /// <summary>Starts a motion for <paramref name="text"/> (null: <see cref="prompt"/>),
        /// cancelling one that plays.</summary>
        public void Play(string text = null)
        {
            Stop();
            var options = new ComGraspStreamOptions();
            if (seed != 0) options.Seed = seed;
            if (chain && lastEnded != 0)
            {
                // Continues from the last motion's end: its place, pose and object (no anchors).
                options.ContinueFrom = lastEnded;
            }
            else
            {
                // Scene anchoring: the motion starts where the character stands, facing its way
                // (the engine's unturned character faces -z: turn it to the avatar's +z first).
                options.CharacterPosition = transform.position;
                options.CharacterRotation = transform.rotation * Quaternion.AngleAxis(180f, Vector3.up);
                if (graspedObject != null)
                {
                    options.ObjectPosition = graspedObject.position;
                    options.ObjectRotation = graspedObject.rotation;
                }
            }
            stream = engine.Start(text ?? prompt, options);
            clock = 0;
            held = false;
            // The motion drives the bones: the Animator's own evaluation would overwrite them.
            animator.enabled = false;
        }

        /// <summary>Stops the motion that plays (the character keeps its last pose).</summary>
        public void Cancel()
        {
            if (stream != null) stream.Cancel();
            Stop();
        }

        void Stop()
        {
            if (stream == null) return;
            stream.Dispose();
            stream = null;
        }

        void Update()
        {
            if (stream == null) return;
            clock += Time.deltaTime;
            // Take the frames due by now (frame.TimeS: seconds from the motion's start) and
            // pose the newest: polling into `next` keeps a frame not yet due from
            // replacing the one shown.
            bool fresh = false;
            while (true)
            {
                if (!held)
                {
                    CgStatus st = stream.Poll(ref next);
                    if (st == CgStatus.End)
                    {
                        lastEnded = stream.Id;
                        Stop();
                        break;
                    }
                    if (st != CgStatus.Ok)
                    {
                        if (st != CgStatus.Pending)
                        {
                            Debug.LogError("ComGrasp: " + st + ": " + ComGraspNative.LastError(), this);
                            Stop();
                        }
                        break; // pending: generation is behind the clock
                    }
                    held = true;
                }
                if (next.TimeS > clock) break;
                frame = next;
                held = false;
                fresh = true;
            }
            if (fresh) Apply();
        }

        unsafe void Apply()
        {
            CgRetargetObject obj;
            retargeter.Retarget(ref frame, poses, out obj);
            // World rotations (parents first), so transforms between humanoid bones don't matter.
            for (int i = 0; i < bones.Length; i++)
            {
                fixed (CgBonePose* p = &poses[i])
                {
                    bones[i].rotation = new Quaternion(p->WorldRotation[0], p->WorldRotation[1], p->WorldRotation[2], p->WorldRotation[3]);
                    if (i == 0) bones[i].position = new Vector3(p->WorldPosition[0], p->WorldPosition[1], p->WorldPosition[2]);
                }
            }
            if (graspedObject != null)
            {
                graspedObject.SetPositionAndRotation(
                    new Vector3(obj.WorldPosition[0], obj.WorldPosition[1], obj.WorldPosition[2]),
                    new Quaternion(obj.WorldRotation[0], obj.WorldRotation[1], obj.WorldRotation[2], obj.WorldRotation[3]));
            }
        }

        void OnDestroy()
        {
            Stop();
            if (retargeter != null) retargeter.Dispose();
            if (engine != null) engine.Dispose();
        }
    }
}
#endif
