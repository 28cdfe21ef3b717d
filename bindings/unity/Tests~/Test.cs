// Test of the Unity package's plain C# (bindings/unity/Runtime: Comgrasp.cs, HumanoidRig.cs)
// against the real library (tests/csharp_binding.rs builds and runs it):
//
//   mcs -unsafe -out:target/tmp/comgrasp_cs_test.exe bindings/unity/Runtime/*.cs 'bindings/unity/Tests~/Test.cs'
//   LD_LIBRARY_PATH=target/debug mono target/tmp/comgrasp_cs_test.exe models/tiny [LAYOUT_FILE]
//
// LAYOUT_FILE is the output of tests/host_support/layout.c (the C compiler's sizes and
// offsets of cg_frame, the config structs and the shared-memory records); without it the
// sizes are checked against the values documented in comgrasp.h only. The shared-memory
// groups publish under a name with this process's id, so parallel runs do not meet. Prints "ok NAME" per check group and a closing
// "csharp: N passed, M failed" line; exit code 0 only when every group passed.
using System;
using System.Collections.Generic;
using System.IO;
using System.Runtime.InteropServices;
using System.Text;
using System.Threading;
using ComGrasp;

static unsafe class ComGraspTest
{
    static string bundle;
    static string layoutFile;
    static int passed, failed;

    static int Main(string[] args)
    {
        if (args.Length < 1)
        {
            Console.Error.WriteLine("usage: Test.exe BUNDLE_DIR [LAYOUT_FILE]");
            return 2;
        }
        bundle = args[0];
        layoutFile = args.Length > 1 ? args[1] : null;

        Run("layout", Layout);
        Run("version", VersionInfo);
        Run("stream_to_end", StreamToEnd);
        Run("polling_allocates_nothing", PollingAllocatesNothing);
        Run("stream_ids_and_determinism", StreamIdsAndDeterminism);
        Run("errors", Errors);
        Run("runtime_options", RuntimeOptions);
        Run("last_error_is_per_thread", LastErrorIsPerThread);
        Run("cancel", Cancel);
        Run("cancel_from_another_thread", CancelFromAnotherThread);
        Run("engine_dispose_cancels_streams", EngineDisposeCancelsStreams);
        Run("shm_subscriber", ShmSubscriber);
        Run("shm_errors", ShmErrors);
        Run("retarget", Retarget);
        Run("humanoid_rig", HumanoidRigTests);
        Run("bvh", Bvh);
        Run("unity_heading", UnityHeading);
        Console.WriteLine("csharp: {0} passed, {1} failed", passed, failed);
        return failed == 0 ? 0 : 1;
    }

    static void Run(string name, Action test)
    {
        try
        {
            test();
            passed++;
            Console.WriteLine("ok " + name);
        }
        catch (Exception e)
        {
            failed++;
            Console.WriteLine("FAILED " + name + ": " + e);
        }
    }

    static void Check(bool cond, string what)
    {
        if (!cond) throw new Exception("check failed: " + what);
    }

    static void Eq<T>(T actual, T expected, string what)
    {
        if (!EqualityComparer<T>.Default.Equals(actual, expected))
            throw new Exception(string.Format("{0}: got {1}, expected {2}", what, actual, expected));
    }

    static ComGraspException Throws(string what, Action a) { return Throws<ComGraspException>(a, what); }

    static ComGraspEngine NewEngine(CgCoordinateSystem coords = CgCoordinateSystem.Native, bool fk = false,
                                    uint? ring = null, uint? maxStreams = null)
    {
        return new ComGraspEngine(new ComGraspEngineOptions
        {
            BundlePath = bundle, Coordinates = coords, EnableFk = fk, RingCapacity = ring, MaxStreams = maxStreams,
        });
    }

    static string Pascal(string snake)
    {
        var sb = new StringBuilder();
        foreach (string part in snake.Split('_'))
            if (part.Length > 0) sb.Append(char.ToUpperInvariant(part[0])).Append(part.Substring(1));
        return sb.ToString();
    }

    // Sizes and field offsets agree with the C compiler's (layout file) and with comgrasp.h.
    static void Layout()
    {
        Eq(sizeof(CgFrame), 1608, "sizeof(CgFrame)");
        Eq(Marshal.SizeOf(typeof(CgFrame)), 1608, "Marshal.SizeOf(CgFrame)");
        Eq(ComGraspNative.cg_frame_size().ToUInt64(), (ulong)sizeof(CgFrame), "cg_frame_size()");
        Eq(ComGraspNative.FrameSize, sizeof(CgFrame), "ComGraspNative.FrameSize");
        Eq(sizeof(CgEngineConfig), IntPtr.Size == 8 ? 80 : 72, "sizeof(CgEngineConfig)");
        Eq(sizeof(CgStreamConfig), 120, "sizeof(CgStreamConfig)");
        Eq(sizeof(CgSubscriberConfig), 16, "sizeof(CgSubscriberConfig)");
        Eq(sizeof(CgStreamEvent), 280, "sizeof(CgStreamEvent)");
        Eq(sizeof(CgSubscriberStats), 48, "sizeof(CgSubscriberStats)");
        Eq(sizeof(CgPublisherStats), 40, "sizeof(CgPublisherStats)");
        Eq((int)Marshal.OffsetOf(typeof(CgEngineConfig), "PublishName"), IntPtr.Size == 8 ? 32 : 28, "offset of PublishName");
        Eq((int)Marshal.OffsetOf(typeof(CgEngineConfig), "StepBackend"), IntPtr.Size == 8 ? 40 : 32, "offset of StepBackend");
        CgEngineConfig ec;
        Eq(ComGraspNative.cg_engine_config_init_sized(&ec, (UIntPtr)sizeof(CgEngineConfig)), CgStatus.Ok, "cg_engine_config_init_sized");
        Eq(ec.StructSize, (uint)sizeof(CgEngineConfig), "cg_engine_config_init's struct_size");
        Eq(ec.PublishName, IntPtr.Zero, "default publish_name");
        CgSubscriberConfig sc;
        Eq(ComGraspNative.cg_subscriber_config_init(&sc), CgStatus.Ok, "cg_subscriber_config_init");
        Eq(sc.StructSize, (uint)sizeof(CgSubscriberConfig), "cg_subscriber_config_init's struct_size");
        Eq(sc.BufferFrames, ComGraspNative.MaxSubscriberBuffer, "default buffer_frames");
        Eq((int)Marshal.OffsetOf(typeof(CgFrame), "JointPositions"), 948, "offset of JointPositions");
        Eq((int)Marshal.OffsetOf(typeof(CgFrame), "Contact"), 940, "offset of Contact");
        if (layoutFile == null) return;

        var types = new Dictionary<string, Type>
        {
            { "cg_frame", typeof(CgFrame) }, { "cg_engine_config", typeof(CgEngineConfig) },
            { "cg_stream_config", typeof(CgStreamConfig) }, { "cg_subscriber_config", typeof(CgSubscriberConfig) },
            { "cg_stream_event", typeof(CgStreamEvent) }, { "cg_subscriber_stats", typeof(CgSubscriberStats) },
            { "cg_publisher_stats", typeof(CgPublisherStats) }, { "cg_stream_info", typeof(CgStreamInfo) },
            { "cg_bone_desc", typeof(CgBoneDesc) }, { "cg_bone_map_entry", typeof(CgBoneMapEntry) },
            { "cg_bone_pose", typeof(CgBonePose) }, { "cg_retarget_object", typeof(CgRetargetObject) },
        };
        var sizes = new Dictionary<Type, int>
        {
            { typeof(CgFrame), sizeof(CgFrame) }, { typeof(CgEngineConfig), sizeof(CgEngineConfig) },
            { typeof(CgStreamConfig), sizeof(CgStreamConfig) }, { typeof(CgSubscriberConfig), sizeof(CgSubscriberConfig) },
            { typeof(CgStreamEvent), sizeof(CgStreamEvent) }, { typeof(CgSubscriberStats), sizeof(CgSubscriberStats) },
            { typeof(CgPublisherStats), sizeof(CgPublisherStats) }, { typeof(CgStreamInfo), sizeof(CgStreamInfo) },
            { typeof(CgBoneDesc), sizeof(CgBoneDesc) }, { typeof(CgBoneMapEntry), sizeof(CgBoneMapEntry) },
            { typeof(CgBonePose), sizeof(CgBonePose) }, { typeof(CgRetargetObject), sizeof(CgRetargetObject) },
        };
        var sized = new HashSet<Type>();
        int facts = 0;
        var seenFields = new Dictionary<Type, int>();
        foreach (string line in File.ReadAllLines(layoutFile))
        {
            string[] w = line.Split(' ');
            if (w.Length == 3 && w[0] == "size")
            {
                Type t = types[w[1]];
                Eq(sizes[t], int.Parse(w[2]), "sizeof " + t.Name + " (C: " + w[1] + ")");
                Eq(Marshal.SizeOf(t), int.Parse(w[2]), "Marshal.SizeOf " + t.Name);
                sized.Add(t);
                facts++;
            }
            else if (w.Length == 4 && w[0] == "offset")
            {
                Type t = types[w[1]];
                string field = Pascal(w[2]);
                Eq((int)Marshal.OffsetOf(t, field), int.Parse(w[3]), "offset of " + t.Name + "." + field + " (C: " + w[2] + ")");
                seenFields[t] = (seenFields.ContainsKey(t) ? seenFields[t] : 0) + 1;
                facts++;
            }
        }
        // Every C field was checked and C# has no extra field.
        foreach (var kv in seenFields)
            Eq(kv.Key.GetFields(System.Reflection.BindingFlags.Instance | System.Reflection.BindingFlags.Public).Length,
               kv.Value, "number of fields of " + kv.Key.Name);
        // Every struct this file declares was in the layout file, with its fields.
        foreach (Type t in sizes.Keys)
        {
            Check(sized.Contains(t), "layout file has the size of " + t.Name);
            Check(seenFields.ContainsKey(t), "layout file has the offsets of " + t.Name);
        }
        Check(facts >= 60, "layout file has " + facts + " facts");
    }

    static readonly int[] SmplxParents = {
        -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
        20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
        21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53 };

    // The engine's own skeleton, its bones named as Unity's HumanBodyBones (the ready map),
    // in Unity coordinates: retargeted world positions are the frames' FK joint positions.
    static unsafe void Retarget()
    {
        var map = ComGraspRetargeter.BuiltinMap(CgBuiltinMap.UnityHumanoid);
        Eq(map.Length, 52, "Unity map entries");
        var byJoint = new Dictionary<string, string>();
        foreach (var kv in map) byJoint[kv.Key] = kv.Value;
        Eq(byJoint["left_wrist"], "LeftHand", "left_wrist -> LeftHand");
        using (var engine = NewEngine(CgCoordinateSystem.Unity, true))
        {
            float[] rest = RestJoints(engine);
            var bones = new ComGraspBone[55];
            for (int j = 0; j < 55; j++)
            {
                int p = SmplxParents[j];
                string name = j < 22 ? byJoint[SmplxJointNames[j]] : "joint" + j;  // the body joints
                var t = new float[3];
                for (int k = 0; k < 3; k++) t[k] = rest[3 * j + k] - (p < 0 ? 0 : rest[3 * p + k]);
                bones[j] = new ComGraspBone { Name = name, Parent = p, RestTranslation = t, RestRotation = new[] { 0f, 0f, 0f, 1f } };
            }
            // (finger bones are unmapped here: they stay at rest, so only the body is compared)
            using (var rt = new ComGraspRetargeter(engine, bones, CgBuiltinMap.UnityHumanoid))
            {
                var poses = new CgBonePose[rt.BoneCount];
                int n = 0;
                foreach (CgFrame frame in AllFrames(engine, "A woman drinks from the mug"))
                {
                    CgFrame f = frame;
                    CgRetargetObject obj;
                    rt.Retarget(ref f, poses, out obj);
                    for (int j = 0; j < 22; j++)
                    {
                        CgBonePose pj = poses[j];
                        for (int k = 0; k < 3; k++)
                            Check(Math.Abs(pj.WorldPosition[k] - f.JointPositions[3 * j + k]) < 1e-3f,
                                  "frame " + n + " joint " + j);
                    }
                    Eq(obj.HandBone[0], 20, "left hand bone");
                    n++;
                }
                Check(n > 0, "frames retargeted");
            }
            var bad = (ComGraspBone[])bones.Clone();
            bad[3].Name = bones[0].Name;
            var e = Throws("duplicate bone", () => new ComGraspRetargeter(engine, bad, CgBuiltinMap.UnityHumanoid));
            Eq(e.Status, CgStatus.ErrInvalidArgument, "duplicate bone status");
            Check(e.NativeMessage.Contains("both named"), e.NativeMessage);
        }
    }

    static readonly string[] SmplxJointNames = {
        "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
        "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
        "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw",
        "left_eye_smplhf", "right_eye_smplhf", "left_index1", "left_index2", "left_index3", "left_middle1",
        "left_middle2", "left_middle3", "left_pinky1", "left_pinky2", "left_pinky3", "left_ring1", "left_ring2",
        "left_ring3", "left_thumb1", "left_thumb2", "left_thumb3", "right_index1", "right_index2", "right_index3",
        "right_middle1", "right_middle2", "right_middle3", "right_pinky1", "right_pinky2", "right_pinky3",
        "right_ring1", "right_ring2", "right_ring3", "right_thumb1", "right_thumb2", "right_thumb3" };

    // The Unity package's HumanoidRig: every bone of the ready Unity map is a HumanBodyBones
    // name with Unity's value; an avatar shaped like the engine's own skeleton (all 52 mapped
    // bones, fingers included) reproduces the frames' joint positions; an avatar without
    // UpperChest and shoulders is parented to the nearest present ancestor; bad avatars throw.
    static unsafe void HumanoidRigTests()
    {
        var map = ComGraspRetargeter.BuiltinMap(CgBuiltinMap.UnityHumanoid);
        foreach (var kv in map)
            Check(HumanoidRig.Parse(kv.Value).HasValue, kv.Value + " is a HumanBodyBones name");
        // (UnityEngine.HumanBodyBones values, from Unity's scripting reference)
        Eq((int)HumanBone.Hips, 0, "Hips");
        Eq((int)HumanBone.LeftHand, 17, "LeftHand");
        Eq((int)HumanBone.Jaw, 23, "Jaw");
        Eq((int)HumanBone.LeftThumbProximal, 24, "LeftThumbProximal");
        Eq((int)HumanBone.RightThumbProximal, 39, "RightThumbProximal");
        Eq((int)HumanBone.RightLittleDistal, 53, "RightLittleDistal");
        Eq((int)HumanBone.UpperChest, 54, "UpperChest");
        Check(!HumanoidRig.Parse("hips").HasValue && !HumanoidRig.Parse("3").HasValue, "only exact names parse");
        Eq(HumanoidRig.ParentOf(HumanBone.LeftIndexIntermediate), (HumanBone?)HumanBone.LeftIndexProximal, "finger parent");
        Eq(HumanoidRig.ParentOf(HumanBone.Hips), (HumanBone?)null, "Hips is the root");

        using (var engine = NewEngine(CgCoordinateSystem.Unity, true))
        {
            float[] rest = RestJoints(engine);
            var jointOf = new Dictionary<HumanBone, int>();
            var avatar = new List<HumanoidBoneRest>();
            foreach (var kv in map)
            {
                HumanBone b = HumanoidRig.Parse(kv.Value).Value;
                int j = Array.IndexOf(SmplxJointNames, kv.Key);
                Check(j >= 0, kv.Key + " is an SMPL-X joint");
                jointOf[b] = j;
                // (a rotated rest frame per bone: the rig must carry it through)
                float a = 0.1f * (int)b, s = (float)Math.Sin(a / 2), c = (float)Math.Cos(a / 2);
                avatar.Add(new HumanoidBoneRest
                {
                    Bone = b,
                    Position = new[] { rest[3 * j], rest[3 * j + 1], rest[3 * j + 2] },
                    Rotation = new[] { s * 0.6f, s * 0.8f, 0f, c },
                });
            }
            avatar.Reverse(); // any order
            var rig = new HumanoidRig(avatar);
            Eq(rig.Bones.Length, 52, "rig bones");
            Eq(rig.Bones[0], HumanBone.Hips, "Hips first");
            for (int i = 0; i < rig.Bones.Length; i++)
                Check(rig.HostBones[i].Parent < i, rig.Bones[i] + " comes after its parent");
            Eq(rig.HostBones[rig.IndexOf(HumanBone.LeftUpperArm)].Parent, rig.IndexOf(HumanBone.LeftShoulder), "arm parent");
            using (var rt = new ComGraspRetargeter(engine, rig.HostBones, CgBuiltinMap.UnityHumanoid))
            {
                var poses = rig.NewPoseBuffer();
                int n = 0;
                float worst = 0;
                foreach (CgFrame frame in AllFrames(engine, "A woman drinks from the mug"))
                {
                    CgFrame f = frame;
                    CgRetargetObject obj;
                    rt.Retarget(ref f, poses, out obj);
                    for (int i = 0; i < rig.Bones.Length; i++)
                    {
                        int j = jointOf[rig.Bones[i]];
                        fixed (CgBonePose* p = &poses[i])
                            for (int k = 0; k < 3; k++)
                                worst = Math.Max(worst, Math.Abs(p->WorldPosition[k] - f.JointPositions[3 * j + k]));
                    }
                    Eq(obj.HandBone[1], rig.IndexOf(HumanBone.RightHand), "right hand bone");
                    n++;
                }
                Check(n > 0, "frames retargeted");
                Check(worst < 1e-3f, "every bone, fingers too, on its joint (worst " + worst + " m)");
            }

            // Without UpperChest and shoulders: nearest present ancestors.
            var lean = avatar.FindAll(b => b.Bone != HumanBone.UpperChest && b.Bone != HumanBone.LeftShoulder && b.Bone != HumanBone.RightShoulder);
            var leanRig = new HumanoidRig(lean);
            Eq(leanRig.HostBones[leanRig.IndexOf(HumanBone.LeftUpperArm)].Parent, leanRig.IndexOf(HumanBone.Chest), "arm on Chest");
            Eq(leanRig.HostBones[leanRig.IndexOf(HumanBone.Neck)].Parent, leanRig.IndexOf(HumanBone.Chest), "neck on Chest");
            using (var rt = new ComGraspRetargeter(engine, leanRig.HostBones, CgBuiltinMap.UnityHumanoid))
                Eq(rt.BoneCount, 49, "lean rig bones");
        }

        var twice = new List<HumanoidBoneRest> { Bone(HumanBone.Hips), Bone(HumanBone.Spine), Bone(HumanBone.Spine) };
        Check(Throws<ArgumentException>(() => new HumanoidRig(twice)).Message.Contains("given twice"), "duplicate bone");
        var noHips = new List<HumanoidBoneRest> { Bone(HumanBone.Spine) };
        Check(Throws<ArgumentException>(() => new HumanoidRig(noHips)).Message.Contains("Hips"), "missing Hips");
        var skewed = Bone(HumanBone.Hips);
        skewed.Rotation = new[] { 0f, 0f, 0f, 2f };
        Check(Throws<ArgumentException>(() => new HumanoidRig(new[] { skewed })).Message.Contains("unit length"), "non-unit rotation");
        var unknown = Bone((HumanBone)99);
        Check(Throws<ArgumentException>(() => new HumanoidRig(new[] { unknown })).Message.Contains("unknown"), "unknown bone");
    }

    static void Bvh()
    {
        using (var engine = NewEngine(CgCoordinateSystem.Unity, true))
        {
            List<CgFrame> frames = AllFrames(engine, "A woman drinks from the mug");
            string dir = Path.Combine(Path.GetTempPath(), "comgrasp-cs-bvh-" + System.Diagnostics.Process.GetCurrentProcess().Id);
            Directory.CreateDirectory(dir);
            string body = Path.Combine(dir, "m.bvh"), obj = Path.Combine(dir, "m.object.bvh");
            engine.WriteBvh(frames.ToArray(), body, obj);
            string text = File.ReadAllText(body);
            Check(text.StartsWith("HIERARCHY\nROOT pelvis\n") && text.Contains("Frames: " + frames.Count + "\n"), "body file");
            Check(File.ReadAllText(obj).StartsWith("HIERARCHY\nROOT object\n"), "object file");
            var e = Throws("missing directory", () => engine.WriteBvh(frames.ToArray(), Path.Combine(dir, "no", "x.bvh")));
            Eq(e.Status, CgStatus.ErrIo, "unwritable path");
            Throws<ArgumentNullException>(() => engine.WriteBvh(null, body));
            Directory.Delete(dir, true);
        }
    }

    // The heading ComGraspAnimator anchors with. The engine's heading is where the pelvis
    // faces (its local +z; in Unity's basis the root rotation turns +y onto it), projected
    // to the ground: unturned it faces -z in Unity coordinates; turned 180 degrees about y
    // (what the animator passes for an avatar facing +z) it faces +z. On the embedded default
    // model: the test bundle's random weights do not stand the pelvis upright.
    static unsafe void UnityHeading()
    {
        using (var engine = new ComGraspEngine(new ComGraspEngineOptions { Coordinates = CgCoordinateSystem.Unity }))
        {
            foreach (bool turned in new[] { false, true })
            {
                var options = new ComGraspStreamOptions
                {
                    CharacterPosition = new CgVec3(0, 0, 0),
                    CharacterRotation = turned ? new CgQuat(0, 1, 0, 0) : new CgQuat(0, 0, 0, 1),
                    MinLen = 1,
                    MaxLen = 1,
                };
                using (var stream = engine.Start("A woman drinks from the mug", options))
                {
                    CgFrame f = default(CgFrame);
                    while (stream.Wait(ref f, 5000) != CgStatus.Ok) { }
                    // v' = v + w t + q x t with t = 2 q x v, for v = (0, 1, 0)
                    float x = f.RootRotation[0], y = f.RootRotation[1], z = f.RootRotation[2], w = f.RootRotation[3];
                    float tx = -2 * z, ty = 0, tz = 2 * x;
                    float fx = w * tx + (y * tz - z * ty), fz = w * tz + (x * ty - y * tx);
                    float n = (float)Math.Sqrt(fx * fx + fz * fz);
                    Check(n > 0.5f && Math.Abs(fx / n) < 1e-3f && (turned ? fz > 0 : fz < 0),
                          (turned ? "turned" : "unturned") + ": pelvis faces (" + fx + ", " + fz + ") on the ground");
                }
            }
        }
    }

    // Every frame of a stream of the prompt, to the end.
    static List<CgFrame> AllFrames(ComGraspEngine engine, string prompt)
    {
        var frames = new List<CgFrame>();
        using (var stream = engine.Start(prompt))
        {
            CgFrame f = default(CgFrame);
            CgStatus st;
            while ((st = stream.Wait(ref f, 5000)) != CgStatus.End)
                if (st == CgStatus.Ok) frames.Add(f);
        }
        return frames;
    }

    // The engine's rest skeleton: 55 joints, x y z each.
    static unsafe float[] RestJoints(ComGraspEngine engine)
    {
        var rest = new float[55 * 3];
        fixed (float* r = rest)
            Eq(ComGraspNative.cg_engine_get_rest_joints(engine.Handle, r, (UIntPtr)55), CgStatus.Ok, "rest joints");
        return rest;
    }

    static HumanoidBoneRest Bone(HumanBone b)
    {
        return new HumanoidBoneRest { Bone = b, Position = new[] { 0f, 0f, 0f }, Rotation = new[] { 0f, 0f, 0f, 1f } };
    }

    static T Throws<T>(Action a, string what = null) where T : Exception
    {
        try { a(); }
        catch (T e) { return e; }
        throw new Exception((what == null ? "" : what + ": ") + "no " + typeof(T).Name);
    }

    static void VersionInfo()
    {
        Eq(ComGraspNative.cg_abi_version(), ComGraspNative.AbiVersion, "cg_abi_version()");
        string v = ComGraspEngine.Version;
        Check(System.Text.RegularExpressions.Regex.IsMatch(v, @"^\d+\.\d+\.\d+"), "version string " + v);
        ComGraspEngine.CheckAbi();
        Eq(ComGraspNative.StatusString(CgStatus.End).Length > 0, true, "status string");
        Eq(ComGraspNative.Utf8ToString(ComGraspNative.cg_status_string(12345)), "unknown cg_status value", "unknown status");
    }

    // One whole stream through Poll: indices, ids, times, flags and values are sane.
    static void StreamToEnd()
    {
        using (var engine = NewEngine(CgCoordinateSystem.Unity, fk: true))
        using (var stream = engine.Start("A woman drinks from the mug", new ComGraspStreamOptions { Seed = 7 }))
        {
            Check(stream.Id >= 1, "stream id >= 1");
            Eq(engine.StreamCount, 1u, "StreamCount");
            CgStreamInfo info = stream.Info;
            Eq(info.StreamId, stream.Id, "info.StreamId");
            Eq(info.GetObjectName(), "mug", "the prompt's object");
            Eq(info.ObjectNamed, 1u, "the prompt names it");
            // Scene anchoring in Unity coordinates: the mug starts where the host puts it.
            var anchored = new ComGraspStreamOptions { Seed = 1, MinLen = 1, MaxLen = 1,
                CharacterPosition = new CgVec3(0, 0, 0), ObjectPosition = new CgVec3(0.1f, 0.8f, -0.55f) };
            using (var a = engine.Start("A woman drinks from the mug", anchored))
            {
                var g = new CgFrame();
                var until = DateTime.UtcNow.AddSeconds(60);
                while (a.Poll(ref g) != CgStatus.Ok) { Check(DateTime.UtcNow < until, "anchored frame"); Thread.Sleep(1); }
                CgVec3 o = g.GetObjectTranslation();
                Check(Math.Abs(o.X - 0.1f) < 1e-5 && Math.Abs(o.Y - 0.8f) < 1e-5 && Math.Abs(o.Z + 0.55f) < 1e-5, "anchored object " + o);
            }
            var e2 = Throws("out of reach", () => engine.Start("a mug", new ComGraspStreamOptions { ObjectPosition = new CgVec3(9, 0.8f, 0) }));
            Eq(e2.Status, CgStatus.ErrInvalidArgument, "out of reach status");
            var f = new CgFrame();
            ulong n = 0;
            bool sawLast = false;
            double lastTime = -1;
            CgStatus st;
            var deadline = DateTime.UtcNow.AddSeconds(120);
            while ((st = stream.Poll(ref f)) != CgStatus.End)
            {
                Check(DateTime.UtcNow < deadline, "stream finished in time");
                if (st == CgStatus.Pending) { Thread.Sleep(1); continue; }
                Eq(st, CgStatus.Ok, "poll status");
                Check(!sawLast, "no frame after the is_last frame");
                Eq(f.FrameIndex, n, "frame_index");
                Eq(f.StreamId, stream.Id, "stream_id");
                Check(f.TimeS > lastTime, "time_s increases");
                lastTime = f.TimeS;
                Eq(f.HasJointPositions, (byte)1, "has_joint_positions with FK");
                CgQuat q = f.GetRootRotation();
                double norm = Math.Sqrt(q.X * q.X + q.Y * q.Y + q.Z * q.Z + q.W * q.W);
                Check(Math.Abs(norm - 1) < 1e-3 && q.W >= 0, "root rotation is a unit quaternion with w >= 0: " + q);
                CgQuat b = f.GetBodyRotation(CgFrame.BodyJoints - 1);
                Check(Math.Abs(Math.Sqrt(b.X * b.X + b.Y * b.Y + b.Z * b.Z + b.W * b.W) - 1) < 1e-3, "body rotation 21 unit");
                for (int h = 0; h < 2; h++)
                {
                    float p = f.GetContactProbability(h);
                    Check(p >= 0 && p <= 1, "contact probability in 0..1");
                    // The contact-consistency stage debounces the flag: it may lag the probability by a few frames.
                    Check(f.GetContact(h) || p < 1.0f, "contact flag is the stage's held state");
                }
                byte* r = f.Reserved;
                Check(r[0] == 0 && r[1] == 0 && r[2] == 0 && r[3] == 0, "reserved bytes are 0");
                sawLast = f.IsLastFrame;
                n++;
            }
            Check(n > 0 && n % 16 == 0, "frames: " + n + " (a multiple of 16)");
            Check(sawLast, "the last frame has is_last = 1");
            Eq(Math.Round(f.TimeS * 30), (double)(n - 1), "time_s = frame_index / fps");
            Eq(stream.Poll(ref f), CgStatus.End, "End repeats");
            Eq(stream.Wait(ref f, 10), CgStatus.End, "Wait after End");
            Console.WriteLine("  {0} frames, last root {1}, object {2}", n, f.GetRootTranslation(), f.GetObjectTranslation());
            stream.Dispose();
            Eq(engine.StreamCount, 0u, "StreamCount after Dispose");
        }
    }

    // Poll/Wait on a reused frame allocate no managed memory (after the first call).
    static void PollingAllocatesNothing()
    {
        using (var engine = NewEngine())
        using (var stream = engine.Start("The man lifts a small cube."))
        {
            var f = new CgFrame();
            CgStatus st = stream.Wait(ref f, 5000);
            stream.PollStatus(ref f);
            long before = GC.GetAllocatedBytesForCurrentThread();
            int frames = 0;
            while ((st = stream.Wait(ref f, 1000)) != CgStatus.End)
            {
                if (st == CgStatus.Ok) frames++;
                if (stream.Poll(ref f) == CgStatus.Ok) frames++;
            }
            long allocated = GC.GetAllocatedBytesForCurrentThread() - before;
            Check(frames > 0, "frames were polled");
            Eq(allocated, 0L, "bytes allocated while polling " + frames + " frames");
        }
    }

    // Ids are distinct per stream; the same seed and text give the same frames.
    static void StreamIdsAndDeterminism()
    {
        using (var engine = NewEngine(CgCoordinateSystem.Gltf))
        {
            var opts = new ComGraspStreamOptions { Seed = 3, Temperature = 0.9, TopK = 4, MinLen = 2, MaxLen = 6 };
            using (var a = engine.Start("The man lifts a small cube.", opts))
            using (var b = engine.Start("The man lifts a small cube.", opts))
            {
                Check(a.Id != b.Id && a.Id >= 1 && b.Id >= 1, "distinct ids " + a.Id + ", " + b.Id);
                Eq(engine.StreamCount, 2u, "two streams alive");
                List<CgFrame> fa = Drain(a), fb = Drain(b);
                Eq(fa.Count, fb.Count, "same frame count");
                Check(fa.Count >= 32 && fa.Count <= 96, "min_len/max_len respected: " + fa.Count);
                for (int i = 0; i < fa.Count; i++)
                {
                    CgFrame x = fa[i], y = fb[i];
                    Eq(x.StreamId, a.Id, "frames of a carry a's id");
                    Eq(y.StreamId, b.Id, "frames of b carry b's id");
                    // Everything after the id must be equal byte for byte.
                    byte* px = (byte*)&x, py = (byte*)&y;
                    for (int k = 8; k < sizeof(CgFrame); k++)
                        if (px[k] != py[k]) throw new Exception("frame " + i + " differs at byte " + k);
                }
            }
        }
    }

    // The runtime options change how the frames are computed (threads, decode grouping,
    // overlap), never which frames: a stream equals the automatic choice's byte for byte.
    static void RuntimeOptions()
    {
        var sopts = new ComGraspStreamOptions { Seed = 5, MinLen = 2, MaxLen = 4 };
        List<CgFrame> auto;
        using (var engine = NewEngine())
        using (var s = engine.Start("The woman picks up the mug.", sopts))
            auto = Drain(s);
        var opts = new ComGraspEngineOptions
        {
            BundlePath = bundle, StepBackend = ComGraspNative.BackendNative, StepThreads = 1, DecoderThreads = 1,
            DecodeGroup = 1, Overlap = ComGraspNative.OverlapOff, MaxIsa = ComGraspNative.IsaBest,
            Scheduling = ComGraspNative.SchedulingPerStream, SchedulerThreads = 1,
        };
        List<CgFrame> manual;
        using (var engine = new ComGraspEngine(opts))
        using (var s = engine.Start("The woman picks up the mug.", sopts))
            manual = Drain(s);
        Eq(manual.Count, auto.Count, "same frame count");
        for (int i = 0; i < auto.Count; i++)
        {
            CgFrame x = auto[i], y = manual[i];
            byte* px = (byte*)&x, py = (byte*)&y;
            for (int k = 8; k < sizeof(CgFrame); k++)
                if (px[k] != py[k]) throw new Exception("frame " + i + " differs at byte " + k);
        }
        var e = Throws("step_threads 3", () => new ComGraspEngine(new ComGraspEngineOptions { BundlePath = bundle, StepThreads = 3 }));
        Eq(e.Status, CgStatus.ErrInvalidArgument, "step_threads 3");
        var es = Throws("scheduling 3", () => new ComGraspEngine(new ComGraspEngineOptions { BundlePath = bundle, Scheduling = 3 }));
        Check(es.NativeMessage.Contains("scheduling"), "message names the field: " + es.NativeMessage);
        Check(e.NativeMessage.Contains("step_threads"), "message names the field: " + e.NativeMessage);
        e = Throws("decode_group 9", () => new ComGraspEngine(new ComGraspEngineOptions
        {
            BundlePath = bundle, DecodeGroup = ComGraspNative.MaxDecodeGroup + 1,
        }));
        Check(e.NativeMessage.Contains("decode_group"), "message names the field: " + e.NativeMessage);
    }

    static List<CgFrame> Drain(ComGraspStream s)
    {
        var list = new List<CgFrame>();
        var f = new CgFrame();
        CgStatus st;
        while ((st = s.Wait(ref f, 1000)) != CgStatus.End)
            if (st == CgStatus.Ok) list.Add(f);
        return list;
    }

    static void Errors()
    {
        // Engine creation.
        var e = Throws("missing bundle", () => new ComGraspEngine(new ComGraspEngineOptions { BundlePath = "/nonexistent/bundle" }));
        Eq(e.Status, CgStatus.ErrBundle, "missing bundle status");
        Check(e.NativeMessage.Contains("/nonexistent/bundle"), "message names the path: " + e.NativeMessage);
        Check(e.Message.StartsWith("cg_engine_create: ErrBundle: "), "exception message: " + e.Message);
        Eq(ComGraspNative.cg_last_error_status(), CgStatus.ErrBundle, "cg_last_error_status");
        e = Throws("ring 0", () => NewEngine(ring: 0));
        Eq(e.Status, CgStatus.ErrInvalidArgument, "ring_capacity 0");

        using (var engine = NewEngine(maxStreams: 2))
        {
            e = Throws("null text", () => engine.Start((string)null));
            Eq(e.Status, CgStatus.ErrNullPointer, "null text status");
            Check(e.NativeMessage.Contains("text"), "null text message: " + e.NativeMessage);
            e = Throws("empty text", () => engine.Start(""));
            Eq(e.Status, CgStatus.ErrInvalidArgument, "empty text status");
            Check(e.NativeMessage.Length > 0, "empty text message");
            Console.WriteLine("  empty text: " + e.NativeMessage);
            e = Throws("blank text", () => engine.Start(" \t "));
            Eq(e.Status, CgStatus.ErrInvalidArgument, "blank text status");
            Check(e.NativeMessage.Contains("whitespace"), "blank text message: " + e.NativeMessage);
            e = Throws("invalid utf-8", () => engine.Start(new byte[] { 0x41, 0xff, 0xfe }));
            Eq(e.Status, CgStatus.ErrInvalidUtf8, "invalid UTF-8 status");
            e = Throws("embedded NUL", () => engine.Start("a\0b"));
            Eq(e.Status, CgStatus.ErrInvalidArgument, "embedded NUL status");
            e = Throws("long text", () => engine.Start(new string('a', ComGraspNative.MaxTextBytes + 1)));
            Eq(e.Status, CgStatus.ErrInvalidArgument, "over-long text status");
            Check(e.NativeMessage.Contains("4096"), "over-long text message: " + e.NativeMessage);
            e = Throws("max_len 0", () => engine.Start("a mug", new ComGraspStreamOptions { MaxLen = 0 }));
            Eq(e.Status, CgStatus.ErrInvalidArgument, "max_len 0 status");

            // The message API: size query, truncating copy, pointer form agree.
            string msg = ComGraspNative.LastError();
            int need = (int)ComGraspNative.cg_last_error_message(null, UIntPtr.Zero).ToUInt32();
            Eq(need, Encoding.UTF8.GetByteCount(msg) + 1, "cg_last_error_message size query");
            byte* buf = stackalloc byte[8];
            ComGraspNative.cg_last_error_message(buf, (UIntPtr)8);
            Eq(buf[7], (byte)0, "truncated copy is NUL-terminated");
            Eq(Encoding.UTF8.GetString(buf, 7), msg.Substring(0, 7), "truncated copy");

            // max_streams.
            using (var s1 = engine.Start("a mug"))
            using (var s2 = engine.Start("a mug"))
            {
                e = Throws("third stream", () => engine.Start("a mug"));
                Eq(e.Status, CgStatus.ErrLimit, "max_streams status");
            }

            // Raw calls with NULL and stale handles: error codes, never a crash.
            var f = new CgFrame();
            Eq(ComGraspNative.cg_poll_frame(IntPtr.Zero, &f), CgStatus.ErrNullPointer, "poll NULL stream");
            Eq(ComGraspNative.cg_engine_create(null, null), CgStatus.ErrNullPointer, "create NULL config");
            var s = engine.Start("a mug");
            IntPtr h = s.Handle;
            Eq(ComGraspNative.cg_poll_frame(h, null), CgStatus.ErrNullPointer, "poll into NULL frame");
            s.Dispose();
            ulong id;
            Eq(ComGraspNative.cg_stream_id(h, &id), CgStatus.ErrInvalidHandle, "stale stream handle");
            Eq(ComGraspNative.cg_stream_destroy(h), CgStatus.ErrInvalidHandle, "double destroy");
            Eq(ComGraspNative.cg_engine_destroy(h), CgStatus.ErrInvalidHandle, "stream handle as engine");
            Check(ComGraspNative.LastError().Length > 0, "stale handle message");
            try
            {
                s.Poll(ref f);
                throw new Exception("Poll on a disposed stream did not throw");
            }
            catch (ObjectDisposedException) { }
            s.Dispose(); // twice is fine
        }
    }

    // The message is thread-local: another thread's failure does not overwrite this one's.
    static void LastErrorIsPerThread()
    {
        using (var engine = NewEngine())
        {
            Throws("blank", () => engine.Start("   "));
            string mine = ComGraspNative.LastError();
            CgStatus other = CgStatus.Ok;
            var t = new Thread(() =>
            {
                try { engine.Start((string)null); } catch (ComGraspException ex) { other = ex.Status; }
            });
            t.Start();
            t.Join();
            Eq(other, CgStatus.ErrNullPointer, "other thread's error");
            Eq(ComGraspNative.LastError(), mine, "this thread's message unchanged");
            Eq(ComGraspNative.cg_last_error_status(), CgStatus.ErrInvalidArgument, "this thread's status unchanged");
        }
    }

    // A 64-frame stream with a 16-frame ring cannot finish before it is drained, so a cancel
    // after the first frame is always seen.
    static void Cancel()
    {
        using (var engine = NewEngine(ring: 16))
        using (var s = engine.Start("A woman drinks from the mug", new ComGraspStreamOptions { MinLen = 4, MaxLen = 4 }))
        {
            var f = new CgFrame();
            Eq(s.Wait(ref f, 30000), CgStatus.Ok, "first frame");
            s.Cancel();
            s.Cancel(); // idempotent
            Eq(s.Poll(ref f), CgStatus.Cancelled, "poll after cancel");
            Eq(s.Poll(ref f), CgStatus.Cancelled, "cancelled repeats");
            Eq(s.Wait(ref f, 10), CgStatus.Cancelled, "wait after cancel");
            Eq(engine.StreamCount, 1u, "a cancelled stream is alive until disposed");
        }
    }

    static void CancelFromAnotherThread()
    {
        using (var engine = NewEngine(ring: 16))
        using (var s = engine.Start("A woman drinks from the mug", new ComGraspStreamOptions { MinLen = 18, MaxLen = 18 }))
        {
            var first = new ManualResetEvent(false);
            var canceller = new Thread(() => { first.WaitOne(); s.Cancel(); });
            canceller.Start();
            var f = new CgFrame();
            CgStatus st;
            int frames = 0;
            while ((st = s.Wait(ref f, 1000)) == CgStatus.Ok || st == CgStatus.Pending)
                if (st == CgStatus.Ok && ++frames == 1) first.Set();
            canceller.Join();
            Eq(st, CgStatus.Cancelled, "status after a cancel from another thread (" + frames + " frames)");
            Check(frames < 18 * 16, "the cancel cut the stream short");
        }
    }

    static void EngineDisposeCancelsStreams()
    {
        var engine = NewEngine(ring: 16);
        var s = engine.Start("A woman drinks from the mug", new ComGraspStreamOptions { MinLen = 4, MaxLen = 4 });
        var f = new CgFrame();
        Eq(s.Wait(ref f, 30000), CgStatus.Ok, "first frame");
        engine.Dispose();
        Eq(s.Poll(ref f), CgStatus.Cancelled, "stream of a disposed engine");
        try
        {
            engine.Start("a mug");
            throw new Exception("Start on a disposed engine did not throw");
        }
        catch (ObjectDisposedException) { }
        s.Dispose();
    }

    /// <summary>A publish name no other process (test run) uses: the pid and a counter.</summary>
    static int shmNames;
    static string UniqueName(string tag)
    {
        return "cs-" + System.Diagnostics.Process.GetCurrentProcess().Id + "-" + tag + "-" + (++shmNames);
    }

    // An engine publishing over shared memory and a subscriber in the same process: the
    // subscriber, opened before the stream starts, receives exactly the polled frames (same
    // ids, indices and bytes), a STARTED and an ENDED event, drops nothing, and receiving
    // allocates no managed memory.
    static void ShmSubscriber()
    {
        const string prompt = "A woman drinks from the mug";
        string name = UniqueName("sub");
        using (var engine = new ComGraspEngine(new ComGraspEngineOptions { BundlePath = bundle, PublishName = name }))
        using (var sub = ComGraspSubscriber.Open(name, ComGraspNative.MaxSubscriberBuffer))
        {
            Eq(engine.PublisherStats.Subscribers, 1UL, "publisher sees the subscriber");
            Eq(sub.Stats.Publishers, 1UL, "subscriber sees the publisher");
            // Preallocated storage, and one call of each function before measuring (the
            // first P/Invoke call of a method may allocate its marshalling stub).
            const int cap = 18 * 16 + 16; // the tiny bundle's l_max tokens of 16 frames, and room
            var polled = new CgFrame[cap];
            var received = new CgFrame[cap + 1];
            var events = new CgStreamEvent[8];
            Eq(sub.TryReceive(ref received[0]), false, "nothing before the stream starts");
            Eq(sub.TryReceiveEvent(ref events[0]), false, "no event before the stream starts");
            var deadline = System.Diagnostics.Stopwatch.StartNew();
            int np = 0, nr = 0, ne = 0;
            using (var stream = engine.Start(prompt, new ComGraspStreamOptions { Seed = 5 }))
            {
                CgStatus st = stream.Wait(ref polled[np], 30000);
                if (st == CgStatus.Ok) np++;
                long before = GC.GetAllocatedBytesForCurrentThread();
                while (st != CgStatus.End)
                {
                    if (np == cap || nr == cap || ne == events.Length || deadline.ElapsedMilliseconds > 120000) break;
                    st = stream.Wait(ref polled[np], 5);
                    if (st == CgStatus.Ok) np++;
                    while (nr < cap && sub.TryReceive(ref received[nr])) nr++;
                    while (ne < events.Length && sub.TryReceiveEvent(ref events[ne])) ne++;
                }
                // Every frame and the ENDED event were published before the stream reported
                // End; they are in this subscriber's queues now (a short grace anyway).
                while ((nr < np || ne < 2) && nr < cap && deadline.ElapsedMilliseconds < 125000)
                {
                    bool any = false;
                    if (sub.TryReceive(ref received[nr])) { nr++; any = true; }
                    if (ne < events.Length && sub.TryReceiveEvent(ref events[ne])) { ne++; any = true; }
                    if (!any) Thread.Yield();
                }
                long allocated = GC.GetAllocatedBytesForCurrentThread() - before;
                Eq(st, CgStatus.End, "stream drained to End (" + np + " frames polled, " + nr + " received)");
                Eq(allocated, 0L, "bytes allocated while polling " + np + " and receiving " + nr + " frames");
                Check(np > 0 && np % 16 == 0, "polled frames: " + np);
                Eq(nr, np, "frames received == frames polled");
                Eq(sub.TryReceive(ref received[nr]), false, "nothing more to receive");
                for (int i = 0; i < np; i++)
                {
                    CgFrame a = polled[i], b = received[i];
                    Eq(b.StreamId, stream.Id, "received stream_id " + i);
                    Eq(b.FrameIndex, (ulong)i, "received frame_index " + i);
                    Eq(b.StreamId, a.StreamId, "stream_id " + i);
                    Eq(b.FrameIndex, a.FrameIndex, "frame_index " + i);
                    Eq(b.TimeS, a.TimeS, "time_s " + i);
                    Eq(b.IsLast, a.IsLast, "is_last " + i);
                    Eq(b.GetRootTranslation().ToString(), a.GetRootTranslation().ToString(), "root translation " + i);
                    Eq(b.GetContactProbability(1), a.GetContactProbability(1), "contact probability " + i);
                    // And the whole struct, byte for byte.
                    byte* pa = (byte*)&a, pb = (byte*)&b;
                    for (int k = 0; k < sizeof(CgFrame); k++)
                        if (pa[k] != pb[k]) throw new Exception("received frame " + i + " differs at byte " + k);
                }
                Eq(received[np - 1].IsLastFrame, true, "the last received frame has is_last");

                Eq(ne, 2, "events received");
                Eq(events[0].Kind, CgStreamEventKind.Started, "first event");
                Eq(events[0].StreamId, stream.Id, "STARTED stream_id");
                Eq(events[0].FrameCount, 0UL, "STARTED frame_count");
                Eq(events[0].Fps, 30f, "STARTED fps");
                Eq(events[0].GetText(), prompt, "STARTED text");
                Eq(ComGraspSubscriber.EventText(ref events[0]), prompt, "EventText");
                Eq(events[1].Kind, CgStreamEventKind.Ended, "second event");
                Eq(events[1].StreamId, stream.Id, "ENDED stream_id");
                Eq(events[1].FrameCount, (ulong)np, "ENDED frame_count");

                CgSubscriberStats ss = sub.Stats;
                Eq(ss.FramesReceived, (ulong)np, "stats frames_received");
                Eq(ss.FramesDropped, 0UL, "stats frames_dropped");
                Eq(ss.EventsReceived, 2UL, "stats events_received");
                Eq(ss.EventsDropped, 0UL, "stats events_dropped");
                Eq(ss.PublisherChanges, 0UL, "stats publisher_changes");
                Eq(ss.Publishers, 1UL, "stats publishers");
                CgPublisherStats ps = engine.PublisherStats;
                Eq(ps.FramesPublished, (ulong)np, "publisher frames_published");
                Eq(ps.FramesSkipped, 0UL, "publisher frames_skipped");
                Eq(ps.EventsPublished, 2UL, "publisher events_published");
                Eq(ps.EventsSkipped, 0UL, "publisher events_skipped");
                Eq(ps.Subscribers, 1UL, "publisher subscribers");
                Console.WriteLine("  {0} frames polled and received, events STARTED/ENDED, 0 dropped", np);
            }

            // Dispose closes; the handle is then stale and the wrapper refuses to use it.
            IntPtr h = sub.Handle;
            sub.Dispose();
            sub.Dispose(); // twice is fine
            Eq(ComGraspNative.cg_subscriber_close(h), CgStatus.ErrInvalidHandle, "double close");
            var f = new CgFrame();
            Eq(ComGraspNative.cg_subscriber_receive(h, &f), CgStatus.ErrInvalidHandle, "receive after close");
            try
            {
                sub.TryReceive(ref f);
                throw new Exception("TryReceive on a disposed subscriber did not throw");
            }
            catch (ObjectDisposedException) { }
            Eq(engine.PublisherStats.Subscribers, 0UL, "publisher sees the subscriber gone");
        }
    }

    static void ShmErrors()
    {
        // No publish name: no publisher counters.
        using (var engine = NewEngine())
        {
            var e = Throws("publisher stats without a name", () => { var unused = engine.PublisherStats; });
            Eq(e.Status, CgStatus.ErrWrongState, "publisher stats without a publish name");
        }
        foreach (string bad in new[] { "", "a/b", "with space", "..", "\u00e9", new string('n', ComGraspNative.MaxPublishNameBytes + 1) })
        {
            var e = Throws("publish name " + bad, () => new ComGraspEngine(new ComGraspEngineOptions { BundlePath = bundle, PublishName = bad }));
            Eq(e.Status, CgStatus.ErrInvalidArgument, "engine with publish name '" + bad + "'");
            e = Throws("subscriber name " + bad, () => ComGraspSubscriber.Open(bad));
            Eq(e.Status, CgStatus.ErrInvalidArgument, "subscriber name '" + bad + "'");
        }
        var ne = Throws("null name", () => ComGraspSubscriber.Open(null));
        Eq(ne.Status, CgStatus.ErrNullPointer, "subscriber with a null name");
        string name = UniqueName("err");
        foreach (uint frames in new uint[] { 0, ComGraspNative.MaxSubscriberBuffer + 1 })
        {
            var e = Throws("buffer " + frames, () => ComGraspSubscriber.Open(name, frames));
            Eq(e.Status, CgStatus.ErrInvalidArgument, "buffer_frames " + frames);
            Check(e.NativeMessage.Contains("buffer_frames"), "buffer message: " + e.NativeMessage);
        }
        // Longest name, smallest buffer: fine, and nothing is pending without a publisher.
        string longest = (name + new string('x', ComGraspNative.MaxPublishNameBytes)).Substring(0, ComGraspNative.MaxPublishNameBytes);
        using (var sub = ComGraspSubscriber.Open(longest, 1))
        {
            var f = new CgFrame();
            var ev = new CgStreamEvent();
            Eq(sub.TryReceive(ref f), false, "no frame without a publisher");
            Eq(sub.TryReceiveEvent(ref ev), false, "no event without a publisher");
            Eq(sub.Stats.Publishers, 0UL, "no publisher yet");
            Eq(ComGraspNative.cg_subscriber_receive(sub.Handle, null), CgStatus.ErrNullPointer, "receive into NULL");
            Eq(ComGraspNative.cg_subscriber_receive_event(sub.Handle, null), CgStatus.ErrNullPointer, "event into NULL");
            Eq(ComGraspNative.cg_subscriber_get_stats(sub.Handle, null), CgStatus.ErrNullPointer, "stats into NULL");
        }
        Eq(ComGraspNative.cg_subscriber_close(IntPtr.Zero), CgStatus.Ok, "closing NULL is a no-op");
        var g = new CgFrame();
        using (var engine = NewEngine())
            Eq(ComGraspNative.cg_subscriber_receive(engine.Handle, &g), CgStatus.ErrInvalidHandle, "an engine is not a subscriber");
    }
}
