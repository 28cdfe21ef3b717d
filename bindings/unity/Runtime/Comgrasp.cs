// Comgrasp.cs: C# binding of the ComGrasp C ABI (include/comgrasp.h), for Unity and .NET.
//
// One file, no dependencies beyond the base class library. It needs unsafe code (the frame
// struct uses fixed buffers, exactly like the C struct): in Unity tick "Allow 'unsafe' Code"
// (Player Settings, or the assembly definition holding this file); with csc/mcs pass -unsafe.
//
// The native library is loaded by name, "comgrasp": libcomgrasp.so (Linux/Android),
// libcomgrasp.dylib (macOS), comgrasp.dll (Windows). In Unity put it under Assets/Plugins/
// (e.g. Assets/Plugins/x86_64/libcomgrasp.so) and select the platform in its import settings.
// On iOS (static library) the DllImport name becomes "__Internal".
//
//   using (var engine = new ComGraspEngine(new ComGraspEngineOptions {
//              BundlePath = "models/tiny", Coordinates = CgCoordinateSystem.Unity }))
//   using (var stream = engine.Start("A woman drinks from the mug")) {
//       var frame = new CgFrame();              // reused: polling never allocates
//       CgStatus st;
//       while ((st = stream.Poll(ref frame)) != CgStatus.End) {   // once per Update()
//           if (st == CgStatus.Ok) { CgVec3 p = frame.GetRootTranslation(); ... }
//       }
//   }
//
// Shared memory (iceoryx2): an engine created with `PublishName = "game"` also publishes
// every frame and stream event; another process (or this one) reads them without running
// the model:
//
//   using (var sub = ComGraspSubscriber.Open("game")) {
//       var frame = new CgFrame(); var ev = new CgStreamEvent();
//       while (sub.TryReceive(ref frame)) { ... frame.StreamId, frame.FrameIndex ... }
//       while (sub.TryReceiveEvent(ref ev)) { ... ev.Kind, ev.GetText() ... }
//   }
//
// Layers: `ComGraspNative` is the raw P/Invoke surface (every cg_* function, pointers and
// status codes as in C). `ComGraspEngine` / `ComGraspStream` / `ComGraspSubscriber` are
// IDisposable wrappers that throw `ComGraspException` (status + the library's thread-local
// message) on errors and poll or receive into a caller-provided `ref CgFrame` without
// allocating. Thread rules are the C ABI's: an engine may be used from any thread; a stream
// or a subscriber from one thread at a time, except ComGraspStream.Cancel(), which any
// thread may call at any time.
using System;
using System.Collections.Generic;
using System.Runtime.InteropServices;
using System.Text;

namespace ComGrasp
{
    /// <summary>Result of every cg_* call (enum cg_status, a 32-bit signed integer).
    /// Non-negative values are normal outcomes, negative values are errors.</summary>
    public enum CgStatus : int
    {
        /// <summary>Success (polling: a frame was written).</summary>
        Ok = 0,
        /// <summary>No frame available yet; poll again later.</summary>
        Pending = 1,
        /// <summary>The stream finished and every frame has been delivered.</summary>
        End = 2,
        /// <summary>The stream was cancelled (Cancel, or its engine was destroyed).</summary>
        Cancelled = 3,
        ErrNullPointer = -1,
        ErrInvalidUtf8 = -2,
        /// <summary>Empty or whitespace-only text, text over CG_MAX_TEXT_BYTES, a bad config value.</summary>
        ErrInvalidArgument = -3,
        /// <summary>Destroyed, never created, or a handle of the wrong type.</summary>
        ErrInvalidHandle = -4,
        /// <summary>The call is not allowed now (e.g. another thread is using the stream).</summary>
        ErrWrongState = -5,
        /// <summary>The model bundle is missing, corrupt or inconsistent.</summary>
        ErrBundle = -6,
        ErrInference = -7,
        ErrIo = -8,
        /// <summary>A limit such as the engine's max_streams is reached.</summary>
        ErrLimit = -9,
        /// <summary>A bug in the library was caught; the handle involved is poisoned.</summary>
        ErrPanic = -10,
        /// <summary>Shared memory (iceoryx2) failed: the publish or subscribe service could not
        /// be created or opened, or receiving failed.</summary>
        ErrShm = -11,
    }

    /// <summary>Coordinate system of an engine's frames (enum cg_coordinate_system).</summary>
    public enum CgCoordinateSystem : int
    {
        /// <summary>z up, right-handed, metres (the bundle's own).</summary>
        Native = 0,
        /// <summary>y up, right-handed, metres.</summary>
        Gltf = 1,
        /// <summary>y up, left-handed, metres: Unity's. Use this in Unity.</summary>
        Unity = 2,
        /// <summary>z up, left-handed, centimetres: Unreal's.</summary>
        Unreal = 3,
    }

    /// <summary>A position or vector (x, y, z), in the engine's coordinate system.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct CgVec3
    {
        public float X, Y, Z;
        public CgVec3(float x, float y, float z) { X = x; Y = y; Z = z; }
        public override string ToString() { return string.Format("({0:F3}, {1:F3}, {2:F3})", X, Y, Z); }
#if UNITY_5_3_OR_NEWER
        public static implicit operator UnityEngine.Vector3(CgVec3 v) { return new UnityEngine.Vector3(v.X, v.Y, v.Z); }
        public static implicit operator CgVec3(UnityEngine.Vector3 v) { return new CgVec3(v.x, v.y, v.z); }
#endif
    }

    /// <summary>A unit quaternion (x, y, z, w), w >= 0.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct CgQuat
    {
        public float X, Y, Z, W;
        public CgQuat(float x, float y, float z, float w) { X = x; Y = y; Z = z; W = w; }
        public override string ToString() { return string.Format("({0:F3}, {1:F3}, {2:F3}, {3:F3})", X, Y, Z, W); }
#if UNITY_5_3_OR_NEWER
        public static implicit operator UnityEngine.Quaternion(CgQuat q) { return new UnityEngine.Quaternion(q.X, q.Y, q.Z, q.W); }
        public static implicit operator CgQuat(UnityEngine.Quaternion q) { return new CgQuat(q.x, q.y, q.z, q.w); }
#endif
    }

    /// <summary>One frame of generated motion: exactly the layout of the C struct cg_frame
    /// (1608 bytes; <see cref="ComGraspNative.FrameSize"/> is checked against the library's
    /// cg_frame_size() when an engine is created). Blittable: passed to the library by pointer,
    /// never copied by the marshaller. The fixed buffers need an unsafe context; the Get*
    /// methods read them from safe code.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public unsafe struct CgFrame
    {
        public const int BodyJoints = 21;
        public const int HandJoints = 15;
        public const int NumJoints = 55;

        /// <summary>Id of the stream that produced the frame (unique per engine).</summary>
        public ulong StreamId;
        /// <summary>0-based index of the frame in its stream.</summary>
        public ulong FrameIndex;
        /// <summary>FrameIndex / fps, seconds.</summary>
        public double TimeS;
        /// <summary>World position of the pelvis (root joint).</summary>
        public fixed float RootTranslation[3];
        /// <summary>Global rotation of the pelvis (x, y, z, w).</summary>
        public fixed float RootRotation[4];
        /// <summary>Local rotations of SMPL-X joints 1..21, [21][4] (x, y, z, w).</summary>
        public fixed float BodyRotations[BodyJoints * 4];
        /// <summary>Local rotations of the left-hand finger joints (SMPL-X 25..39), [15][4].</summary>
        public fixed float LeftHandRotations[HandJoints * 4];
        /// <summary>Local rotations of the right-hand finger joints (SMPL-X 40..54), [15][4].</summary>
        public fixed float RightHandRotations[HandJoints * 4];
        /// <summary>World position of the object's origin.</summary>
        public fixed float ObjectTranslation[3];
        /// <summary>Global rotation of the object (x, y, z, w).</summary>
        public fixed float ObjectRotation[4];
        /// <summary>World position of the object's bounding-box centre.</summary>
        public fixed float ObjectCentre[3];
        /// <summary>Left wrist position minus the object centre.</summary>
        public fixed float LeftWristToObject[3];
        /// <summary>Right wrist position minus the object centre.</summary>
        public fixed float RightWristToObject[3];
        /// <summary>Contact probability per hand [left, right], 0..1.</summary>
        public fixed float ContactProbability[2];
        /// <summary>Contact flag per hand [left, right], 0 or 1.</summary>
        public fixed byte Contact[2];
        /// <summary>1 on the last frame of the stream, else 0.</summary>
        public byte IsLast;
        /// <summary>1 when JointPositions is filled (forward kinematics enabled).</summary>
        public byte HasJointPositions;
        /// <summary>Padding, always 0.</summary>
        public fixed byte Reserved[4];
        /// <summary>World positions of the 55 SMPL-X joints, [55][3] (only when HasJointPositions is 1).</summary>
        public fixed float JointPositions[NumJoints * 3];

        public bool IsLastFrame { get { return IsLast != 0; } }

        public CgVec3 GetRootTranslation() { fixed (float* p = RootTranslation) return V3(p, 0, 1); }
        public CgQuat GetRootRotation() { fixed (float* p = RootRotation) return Q(p, 0, 1); }
        /// <summary>Local rotation of SMPL-X joint <paramref name="index"/> + 1 (index 0..20).</summary>
        public CgQuat GetBodyRotation(int index) { fixed (float* p = BodyRotations) return Q(p, index, BodyJoints); }
        /// <summary>Local rotation of left-hand finger joint <paramref name="index"/> (0..14 = SMPL-X 25..39).</summary>
        public CgQuat GetLeftHandRotation(int index) { fixed (float* p = LeftHandRotations) return Q(p, index, HandJoints); }
        /// <summary>Local rotation of right-hand finger joint <paramref name="index"/> (0..14 = SMPL-X 40..54).</summary>
        public CgQuat GetRightHandRotation(int index) { fixed (float* p = RightHandRotations) return Q(p, index, HandJoints); }
        public CgVec3 GetObjectTranslation() { fixed (float* p = ObjectTranslation) return V3(p, 0, 1); }
        public CgQuat GetObjectRotation() { fixed (float* p = ObjectRotation) return Q(p, 0, 1); }
        public CgVec3 GetObjectCentre() { fixed (float* p = ObjectCentre) return V3(p, 0, 1); }
        public CgVec3 GetLeftWristToObject() { fixed (float* p = LeftWristToObject) return V3(p, 0, 1); }
        public CgVec3 GetRightWristToObject() { fixed (float* p = RightWristToObject) return V3(p, 0, 1); }
        /// <summary>Contact probability of hand 0 (left) or 1 (right).</summary>
        public float GetContactProbability(int hand) { Check(hand, 2); fixed (float* p = ContactProbability) return p[hand]; }
        /// <summary>Contact flag of hand 0 (left) or 1 (right).</summary>
        public bool GetContact(int hand) { Check(hand, 2); fixed (byte* p = Contact) return p[hand] != 0; }
        /// <summary>World position of SMPL-X joint <paramref name="joint"/> (0..54; zero unless HasJointPositions).</summary>
        public CgVec3 GetJointPosition(int joint) { fixed (float* p = JointPositions) return V3(p, joint, NumJoints); }

        static void Check(int i, int n)
        {
            if ((uint)i >= (uint)n) throw new ArgumentOutOfRangeException("index", i, "must be 0.." + (n - 1));
        }
        static CgVec3 V3(float* p, int i, int n) { Check(i, n); p += 3 * i; return new CgVec3(p[0], p[1], p[2]); }
        static CgQuat Q(float* p, int i, int n) { Check(i, n); p += 4 * i; return new CgQuat(p[0], p[1], p[2], p[3]); }
    }

    /// <summary>struct cg_engine_config. Fill with cg_engine_config_init before changing fields.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct CgEngineConfig
    {
        public uint StructSize;
        public CgCoordinateSystem CoordinateSystem;
        /// <summary>const char*: NUL-terminated UTF-8, borrowed during cg_engine_create only; IntPtr.Zero = default bundle.</summary>
        public IntPtr BundlePath;
        public uint EnableFk;
        public uint RingCapacity;
        public uint MaxStreams;
        public uint Reserved;
        /// <summary>const char*: the publish name (NUL-terminated ASCII letters, digits, '_', '-', '.';
        /// 1..64 bytes), borrowed during cg_engine_create only; IntPtr.Zero = no shared memory.
        /// Appended after the first version (an older library's init leaves StructSize at 32).</summary>
        public IntPtr PublishName;
        // Runtime options (library 0.3; an older library's init leaves StructSize at 40): 0 is
        // automatic everywhere. See cg_engine_config in comgrasp.h for each field.
        /// <summary>CG_BACKEND_AUTO (0), CG_BACKEND_NATIVE (1) or CG_BACKEND_TRACT (2).</summary>
        public uint StepBackend;
        /// <summary>CG_BACKEND_AUTO (0), CG_BACKEND_NATIVE (1) or CG_BACKEND_TRACT (2).</summary>
        public uint DecoderBackend;
        /// <summary>0 automatic, 1 or 2.</summary>
        public uint StepThreads;
        /// <summary>0 automatic, 1 or 2.</summary>
        public uint DecoderThreads;
        /// <summary>0 automatic, 1..8 tokens per decode.</summary>
        public uint DecodeGroup;
        /// <summary>CG_OVERLAP_AUTO (0), CG_OVERLAP_OFF (1) or CG_OVERLAP_ON (2).</summary>
        public uint Overlap;
        /// <summary>CG_ISA_BEST (0), CG_ISA_PORTABLE (1), CG_ISA_AVX2 (2) or CG_ISA_AVX512 (3); process-wide.</summary>
        public uint MaxIsa;
        public uint Reserved2;
        // Library 0.4 (an older library's init leaves StructSize short of these).
        /// <summary>CG_SCHEDULING_AUTO (0, the crowd scheduler), CG_SCHEDULING_CROWD (1) or CG_SCHEDULING_PER_STREAM (2).</summary>
        public uint Scheduling;
        /// <summary>Crowd scheduler threads: 0 automatic (cores minus one), 1..CG_MAX_SCHEDULER_THREADS.</summary>
        public uint SchedulerThreads;
    }

    /// <summary>struct cg_stream_config. Fill with cg_stream_config_init; to override a field set
    /// it AND clear its UseDefault* bit in UseDefaults.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public unsafe struct CgStreamConfig
    {
        public const uint UseDefaultSeed = 1u << 0;
        public const uint UseDefaultTemperature = 1u << 1;
        public const uint UseDefaultTopK = 1u << 2;
        public const uint UseDefaultMinLen = 1u << 3;
        public const uint UseDefaultMaxLen = 1u << 4;
        public const uint UseDefaultGuidance = 1u << 5;
        public const uint UseDefaultAll = 63;

        public uint StructSize;
        public uint UseDefaults;
        public ulong Seed;
        public double Temperature;
        public uint TopK;
        public uint MinLen;
        public uint MaxLen;
        /// <summary>Bitmask of the Flag* constants (cg_stream_config.flags).</summary>
        public uint Flags;
        /// <summary>CG_STREAM_RAW_OUTPUT: the model's frames without the contact-consistency stage.</summary>
        public const uint FlagRawOutput = 1u << 0;
        /// <summary>CG_STREAM_NO_GRASP_PLACEMENT: the resting object stays where the model put it (not where its hand first closes).</summary>
        public const uint FlagNoGraspPlacement = 1u << 1;
        /// <summary>CG_STREAM_FREE_FEET: the model's legs as they are (its feet may slide), not planted.</summary>
        public const uint FlagFreeFeet = 1u << 2;
        /// <summary>CG_ANCHOR_*: bits of Anchor.</summary>
        public const uint AnchorCharacter = 1u << 0;
        public const uint AnchorObject = 1u << 1;
        public const uint AnchorPlaceCharacter = 1u << 2;
        /// <summary>Scene anchoring (CG_ANCHOR_* bits); positions and rotations below in the engine's coordinates.</summary>
        public uint Anchor;
        public uint Reserved;
        /// <summary>The character's ground point (under the pelvis at the first frame).</summary>
        public fixed float CharacterPosition[3];
        /// <summary>Its heading (only the turn about the up axis counts; identity faces native +y = Unity -z).</summary>
        public fixed float CharacterRotation[4];
        /// <summary>The object's start (its origin) and rotation.</summary>
        public fixed float ObjectPosition[3];
        public fixed float ObjectRotation[4];
        /// <summary>Non-zero: continue the ended stream with this id (its pose, place and object).</summary>
        public ulong ContinueFrom;
        /// <summary>Classifier-free guidance scale, >= 0 (1: the prompt alone).</summary>
        public double Guidance;
    }

    /// <summary>struct cg_subscriber_config. Fill with cg_subscriber_config_init before changing fields.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct CgSubscriberConfig
    {
        public uint StructSize;
        /// <summary>Frames kept between two reads, 1..CG_MAX_SUBSCRIBER_BUFFER (256, the default);
        /// when full the oldest is overwritten and counted in FramesDropped.</summary>
        public uint BufferFrames;
        /// <summary>Must be 0.</summary>
        public ulong Reserved;
    }

    /// <summary>cg_stream_event.kind (CG_STREAM_EVENT_*).</summary>
    public enum CgStreamEventKind : uint
    {
        /// <summary>The stream started (its first frame follows).</summary>
        Started = 1,
        /// <summary>The stream ended; FrameCount frames were generated.</summary>
        Ended = 2,
        /// <summary>The stream was cancelled after FrameCount frames.</summary>
        Cancelled = 3,
        /// <summary>The stream's worker failed after FrameCount frames.</summary>
        Failed = 4,
    }

    /// <summary>struct cg_bone_desc: one bone of a host skeleton (docs/retargeting.md).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public unsafe struct CgBoneDesc
    {
        /// <summary>NUL-terminated UTF-8 name (keep the memory alive during the create call).</summary>
        public IntPtr Name;
        /// <summary>Index of the parent bone, -1 for a root.</summary>
        public int Parent;
        /// <summary>Rest position relative to the parent (engine coordinate system and units).</summary>
        public fixed float RestTranslation[3];
        /// <summary>Rest rotation relative to the parent (x, y, z, w).</summary>
        public fixed float RestRotation[4];
    }

    /// <summary>struct cg_bone_map_entry: which bone follows which SMPL-X joint.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct CgBoneMapEntry
    {
        /// <summary>NUL-terminated SMPL-X joint name.</summary>
        public IntPtr SmplxJoint;
        /// <summary>NUL-terminated bone name.</summary>
        public IntPtr Bone;
    }

    /// <summary>struct cg_bone_pose: one bone's transform in a retargeted frame.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public unsafe struct CgBonePose
    {
        /// <summary>Relative to the parent: set these on the rig.</summary>
        public fixed float LocalTranslation[3];
        /// <summary>(x, y, z, w).</summary>
        public fixed float LocalRotation[4];
        /// <summary>In the world.</summary>
        public fixed float WorldPosition[3];
        /// <summary>(x, y, z, w).</summary>
        public fixed float WorldRotation[4];
    }

    /// <summary>struct cg_retarget_object: the object in the world and in each hand bone's frame.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public unsafe struct CgRetargetObject
    {
        /// <summary>The object's origin in the world.</summary>
        public fixed float WorldPosition[3];
        /// <summary>(x, y, z, w).</summary>
        public fixed float WorldRotation[4];
        /// <summary>[left, right][3]: in hand bone HandBone[h]'s frame.</summary>
        public fixed float InHandPosition[6];
        /// <summary>[left, right][4] (x, y, z, w).</summary>
        public fixed float InHandRotation[8];
        /// <summary>Bone index of each hand, -1 when its wrist is unmapped.</summary>
        public fixed int HandBone[2];
        /// <summary>1 while that hand holds the object.</summary>
        public fixed byte Contact[2];
        /// <summary>Zero.</summary>
        public fixed byte Reserved[6];
    }

    /// <summary>enum cg_builtin_map: the ready SMPL-X-to-rig maps.</summary>
    public enum CgBuiltinMap
    {
        /// <summary>Unity HumanBodyBones names.</summary>
        UnityHumanoid = 1,
        /// <summary>The UE5 Mannequin.</summary>
        Ue5Mannequin = 2,
        /// <summary>Mixamo (mixamorig:).</summary>
        Mixamo = 3,
    }

    /// <summary>struct cg_stream_info (80 bytes): what a stream is about (cg_stream_get_info).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public unsafe struct CgStreamInfo
    {
        /// <summary>CG_OBJECT_NAME_MAX + 1: bytes of ObjectName, the terminating NUL included.</summary>
        public const int ObjectNameBytes = 64;

        /// <summary>The stream's id.</summary>
        public ulong StreamId;
        /// <summary>Index of the stream's object in the bundle's catalogue.</summary>
        public uint ObjectIndex;
        /// <summary>1 when the prompt names the object; 0 when it names none and the first catalogue object stands in.</summary>
        public uint ObjectNamed;
        /// <summary>The catalogue name, NUL-terminated ASCII/UTF-8.</summary>
        public fixed byte ObjectName[ObjectNameBytes];

        /// <summary>The catalogue name as a string (allocates it).</summary>
        public string GetObjectName()
        {
            fixed (byte* p = ObjectName) return ComGraspNative.Utf8ToString(p, ObjectNameBytes);
        }
    }

    /// <summary>struct cg_stream_event (280 bytes): a stream's lifecycle record, received with
    /// <see cref="ComGraspSubscriber.TryReceiveEvent"/>. Blittable, like CgFrame.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public unsafe struct CgStreamEvent
    {
        /// <summary>CG_EVENT_TEXT_BYTES: bytes of Text, the terminating NUL included.</summary>
        public const int TextBytes = 256;

        /// <summary>The stream's id (the StreamId of its frames).</summary>
        public ulong StreamId;
        /// <summary>Frames generated when the event was sent (0 for Started; the total for Ended).</summary>
        public ulong FrameCount;
        public CgStreamEventKind Kind;
        /// <summary>Frames per second of the engine's model (TimeS = FrameIndex / Fps).</summary>
        public float Fps;
        /// <summary>The prompt, UTF-8, NUL-terminated (at most 255 bytes); read it with GetText().</summary>
        public fixed byte Text[TextBytes];

        /// <summary>The prompt as a string (allocates it; the bytes up to the first NUL).</summary>
        public string GetText()
        {
            fixed (byte* p = Text) return ComGraspNative.Utf8ToString(p, TextBytes);
        }
    }

    /// <summary>struct cg_subscriber_stats: counters of a subscriber since it was opened.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct CgSubscriberStats
    {
        public ulong FramesReceived;
        /// <summary>Frames lost: overwritten (this subscriber read too slowly) or skipped by the publisher.</summary>
        public ulong FramesDropped;
        public ulong EventsReceived;
        public ulong EventsDropped;
        /// <summary>Times the frames started coming from another publisher.</summary>
        public ulong PublisherChanges;
        /// <summary>Frame publishers connected right now.</summary>
        public ulong Publishers;
    }

    /// <summary>struct cg_publisher_stats: counters of an engine's shared-memory publisher.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct CgPublisherStats
    {
        public ulong FramesPublished;
        /// <summary>Frames skipped because no shared-memory sample was free (never waited for).</summary>
        public ulong FramesSkipped;
        public ulong EventsPublished;
        public ulong EventsSkipped;
        /// <summary>Frame subscribers connected right now, in all processes.</summary>
        public ulong Subscribers;
    }

    /// <summary>The raw C ABI: one declaration per cg_* function of comgrasp.h. Handles are
    /// IntPtr (opaque; the library validates them, so a stale one gives ErrInvalidHandle).</summary>
    public static unsafe class ComGraspNative
    {
#if (UNITY_IOS || UNITY_WEBGL) && !UNITY_EDITOR
        public const string Lib = "__Internal";
#else
        public const string Lib = "comgrasp";
#endif
        /// <summary>CG_ABI_VERSION of the header this file mirrors.</summary>
        public const uint AbiVersion = 1;
        /// <summary>sizeof(cg_frame) in the header this file mirrors.</summary>
        public const int FrameSize = 1608;
        /// <summary>CG_MAX_TEXT_BYTES: longest accepted prompt in UTF-8 bytes.</summary>
        public const int MaxTextBytes = 4096;
        /// <summary>CG_MAX_PUBLISH_NAME_BYTES: longest accepted publish name in bytes.</summary>
        public const int MaxPublishNameBytes = 64;
        /// <summary>CG_MAX_SUBSCRIBER_BUFFER: largest subscriber buffer, in frames (the default).</summary>
        public const uint MaxSubscriberBuffer = 256;
        /// <summary>CG_BACKEND_*: cg_engine_config.step_backend / decoder_backend.</summary>
        public const uint BackendAuto = 0, BackendNative = 1, BackendTract = 2;
        /// <summary>CG_OVERLAP_*: cg_engine_config.overlap.</summary>
        public const uint OverlapAuto = 0, OverlapOff = 1, OverlapOn = 2;
        /// <summary>CG_ISA_*: cg_engine_config.max_isa.</summary>
        public const uint IsaBest = 0, IsaPortable = 1, IsaAvx2 = 2, IsaAvx512 = 3;
        /// <summary>CG_SCHEDULING_*: cg_engine_config.scheduling.</summary>
        public const uint SchedulingAuto = 0, SchedulingCrowd = 1, SchedulingPerStream = 2;
        /// <summary>CG_MAX_SCHEDULER_THREADS: largest cg_engine_config.scheduler_threads.</summary>
        public const uint MaxSchedulerThreads = 64;
        /// <summary>CG_MAX_DECODE_GROUP: largest cg_engine_config.decode_group.</summary>
        public const uint MaxDecodeGroup = 8;

        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern uint cg_abi_version();
        /// <summary>Static NUL-terminated string; see <see cref="ComGraspEngine.Version"/>.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern IntPtr cg_version_string();
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern UIntPtr cg_frame_size();
        /// <summary>Static NUL-terminated description of a status code.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern IntPtr cg_status_string(int status);
        /// <summary>The calling thread's last error message (valid until its next failing call).</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern IntPtr cg_last_error();
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern UIntPtr cg_last_error_message(byte* buf, UIntPtr len);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_last_error_status();
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_engine_config_init_sized(CgEngineConfig* cfg, UIntPtr size);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_stream_config_init(CgStreamConfig* cfg);

        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_stream_config_init_sized(CgStreamConfig* cfg, UIntPtr size);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_engine_create(CgEngineConfig* cfg, IntPtr* engine);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_engine_destroy(IntPtr engine);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_engine_stream_count(IntPtr engine, uint* count);
        /// <summary>text: NUL-terminated UTF-8.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_start(IntPtr engine, byte* text, CgStreamConfig* cfg, IntPtr* stream);
        /// <summary>text: len bytes of UTF-8, no NUL needed.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_start_utf8(IntPtr engine, byte* text, UIntPtr len, CgStreamConfig* cfg, IntPtr* stream);
        /// <summary>Never blocks, never allocates.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_poll_frame(IntPtr stream, CgFrame* frame);
        /// <summary>Blocks up to timeoutMs; never on a game's main thread.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_stream_wait(IntPtr stream, uint timeoutMs, CgFrame* frame);
        /// <summary>Any thread, any time; idempotent.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_cancel(IntPtr stream);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_stream_destroy(IntPtr stream);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_stream_id(IntPtr stream, ulong* id);

        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_stream_get_info(IntPtr stream, CgStreamInfo* info);
        /// <summary>out: CgFrame.NumJoints x 3 floats.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_engine_get_rest_joints(IntPtr engine, float* rest, UIntPtr n);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_engine_write_bvh(IntPtr engine, CgFrame* frames, UIntPtr nFrames, byte* bodyPath, byte* objectPath);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_builtin_map_size(int which, UIntPtr* count);
        /// <summary>Writes two static NUL-terminated strings.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_builtin_map_entry(int which, UIntPtr index, IntPtr* smplxJoint, IntPtr* bone);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_retargeter_create(IntPtr engine, CgBoneDesc* bones, UIntPtr nBones,
                                                           CgBoneMapEntry* map, UIntPtr nMap, IntPtr* retargeter);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_retargeter_create_builtin(IntPtr engine, CgBoneDesc* bones, UIntPtr nBones,
                                                                   int which, IntPtr* retargeter);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_retargeter_destroy(IntPtr retargeter);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_retargeter_bone_count(IntPtr retargeter, UIntPtr* count);
        /// <summary>Allocation-free; obj may be NULL.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_retarget_frame(IntPtr retargeter, CgFrame* frame, CgBonePose* poses,
                                                        UIntPtr nPoses, CgRetargetObject* obj);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_subscriber_config_init(CgSubscriberConfig* cfg);
        /// <summary>name: NUL-terminated publish name; cfg may be NULL (defaults).</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_subscriber_open(byte* name, CgSubscriberConfig* cfg, IntPtr* subscriber);
        /// <summary>Ok (frame written) or Pending (none); never blocks, never allocates.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_subscriber_receive(IntPtr subscriber, CgFrame* frame);
        /// <summary>Ok (event written) or Pending (none); never blocks.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_subscriber_receive_event(IntPtr subscriber, CgStreamEvent* ev);
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_subscriber_get_stats(IntPtr subscriber, CgSubscriberStats* stats);
        /// <summary>NULL is ignored; a closed handle gives ErrInvalidHandle.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_subscriber_close(IntPtr subscriber);
        /// <summary>ErrWrongState when the engine has no publish name.</summary>
        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern CgStatus cg_engine_publisher_stats(IntPtr engine, CgPublisherStats* stats);

        /// <summary>A NUL-terminated UTF-8 C string as a .NET string ("" for NULL).</summary>
        /// <summary>The UTF-8 bytes of a fixed buffer up to its first NUL (or its end).</summary>
        public static string Utf8ToString(byte* p, int max)
        {
            int n = 0;
            while (n < max && p[n] != 0) n++;
            return Encoding.UTF8.GetString(p, n);
        }

        public static string Utf8ToString(IntPtr p)
        {
            if (p == IntPtr.Zero) return "";
            byte* s = (byte*)p;
            int n = 0;
            while (s[n] != 0) n++;
            return Encoding.UTF8.GetString(s, n);
        }

        /// <summary>The calling thread's last error message, copied.</summary>
        public static string LastError() { return Utf8ToString(cg_last_error()); }

        /// <summary>The status code's description (cg_status_string).</summary>
        public static string StatusString(CgStatus status) { return Utf8ToString(cg_status_string((int)status)); }

        /// <summary><paramref name="s"/> as NUL-terminated UTF-8, for a `fixed` pin during one call.</summary>
        internal static byte[] NulTerminated(string s)
        {
            byte[] b = new byte[Encoding.UTF8.GetByteCount(s) + 1];
            Encoding.UTF8.GetBytes(s, 0, s.Length, b, 0);
            return b;
        }
    }

    /// <summary>A failed cg_* call: its status and the library's message, copied on the
    /// calling thread right after the call.</summary>
    public sealed class ComGraspException : Exception
    {
        public CgStatus Status { get; private set; }
        /// <summary>The library's message alone (Message also names the call and status).</summary>
        public string NativeMessage { get; private set; }

        public ComGraspException(string call, CgStatus status, string nativeMessage)
            : base(call + ": " + status + ": " + nativeMessage)
        {
            Status = status;
            NativeMessage = nativeMessage;
        }

        /// <summary>Throws for errors (negative codes); passes normal outcomes through.</summary>
        internal static CgStatus Check(string call, CgStatus status)
        {
            if ((int)status < 0) throw new ComGraspException(call, status, ComGraspNative.LastError());
            return status;
        }
    }

    /// <summary>Engine settings (see struct cg_engine_config); null fields keep the defaults.</summary>
    public sealed class ComGraspEngineOptions
    {
        /// <summary>Model bundle directory; null: $COMGRASP_BUNDLE, else the bundle embedded in the library.</summary>
        public string BundlePath;
        public CgCoordinateSystem Coordinates = CgCoordinateSystem.Native;
        /// <summary>Fill CgFrame.JointPositions by forward kinematics.</summary>
        public bool EnableFk;
        /// <summary>Frames buffered per stream, 1..65536 (default 256).</summary>
        public uint? RingCapacity;
        /// <summary>Streams alive at once, 1..1024 (default 16).</summary>
        public uint? MaxStreams;
        /// <summary>Also publish every frame and stream event over shared memory under this name
        /// (1..64 ASCII letters, digits, '_', '-', '.'), for <see cref="ComGraspSubscriber"/>s in
        /// any process; null (default): no shared memory.</summary>
        public string PublishName;
        /// <summary>Runtime options (library 0.3; see cg_engine_config in comgrasp.h); null keeps
        /// the automatic choice. Backends: ComGraspNative.BackendNative/BackendTract.</summary>
        public uint? StepBackend, DecoderBackend;
        /// <summary>Threads of the step / decoder, 1 or 2.</summary>
        public uint? StepThreads, DecoderThreads;
        /// <summary>Tokens per decode, 1..ComGraspNative.MaxDecodeGroup.</summary>
        public uint? DecodeGroup;
        /// <summary>ComGraspNative.OverlapOff / OverlapOn.</summary>
        public uint? Overlap;
        /// <summary>Highest instruction set, process-wide: ComGraspNative.IsaPortable/IsaAvx2/IsaAvx512.</summary>
        public uint? MaxIsa;
        /// <summary>Library 0.4: ComGraspNative.SchedulingCrowd (a few threads for every stream, token
        /// steps batched; the default) or SchedulingPerStream (a thread per stream).</summary>
        public uint? Scheduling;
        /// <summary>Library 0.4: crowd scheduler threads, 1..ComGraspNative.MaxSchedulerThreads
        /// (default: cores minus one, so the game keeps a core).</summary>
        public uint? SchedulerThreads;
    }

    /// <summary>Sampling overrides of one stream; null fields keep the bundle's defaults.</summary>
    public struct ComGraspStreamOptions
    {
        public ulong? Seed;
        public double? Temperature;
        public uint? TopK;
        /// <summary>End not allowed before this many token steps (16 frames each).</summary>
        public uint? MinLen;
        /// <summary>End forced at this many token steps.</summary>
        public uint? MaxLen;
        /// <summary>The model's raw frames, without the contact-consistency stage (the object
        /// may float or drift). Default false.</summary>
        public bool RawOutput;
        /// <summary>The resting object stays where the model put it, not where its hand first
        /// closes on it (placement from the grasp holds the first frame back until that grasp).
        /// Default false.</summary>
        public bool NoGraspPlacement;
        /// <summary>The model's legs are left as they are, so its feet may slide (for a host that
        /// runs its own foot IK, e.g. on uneven ground); by default a foot the model stands on
        /// stays planted. Default false.</summary>
        public bool FreeFeet;
        /// <summary>Scene anchoring: the character's ground point and heading in the engine's
        /// coordinates (e.g. its Unity transform's position and rotation).</summary>
        public CgVec3? CharacterPosition;
        /// <summary>Null: the identity.</summary>
        public CgQuat? CharacterRotation;
        /// <summary>Scene anchoring: where the object starts; the character reaches for it
        /// (within 0.8 m and 0.3-1.6 m above its ground point).</summary>
        public CgVec3? ObjectPosition;
        /// <summary>Null: the identity.</summary>
        public CgQuat? ObjectRotation;
        /// <summary>With ObjectPosition and no CharacterPosition: the character comes to the object.</summary>
        public bool PlaceCharacter;
        /// <summary>Continue from the ended stream with this id (ComGraspStream.Id): its pose, place and object.</summary>
        public ulong? ContinueFrom;
        /// <summary>Classifier-free guidance scale, >= 0 (1: the prompt alone). Null: the bundle's default.</summary>
        public double? Guidance;
    }

    /// <summary>A loaded model bundle (cg_engine). Create once (it takes a fraction of a second),
    /// start many streams. Dispose cancels the streams still generating (they then report
    /// Cancelled) and frees the model; their ComGraspStream objects stay valid.</summary>
    public sealed unsafe class ComGraspEngine : IDisposable
    {
        IntPtr handle;

        /// <summary>The library's version, "MAJOR.MINOR.PATCH".</summary>
        public static string Version { get { return ComGraspNative.Utf8ToString(ComGraspNative.cg_version_string()); } }

        /// <summary>Throws if the loaded library does not match this file (ABI version or frame size).</summary>
        public static void CheckAbi()
        {
            uint abi = ComGraspNative.cg_abi_version();
            ulong size = ComGraspNative.cg_frame_size().ToUInt64();
            if (abi != ComGraspNative.AbiVersion || size != (ulong)sizeof(CgFrame) || sizeof(CgFrame) != ComGraspNative.FrameSize)
                throw new InvalidOperationException(string.Format(
                    "comgrasp: library ABI {0} / frame size {1} does not match Comgrasp.cs (ABI {2}, frame {3} bytes)",
                    abi, size, ComGraspNative.AbiVersion, sizeof(CgFrame)));
        }

        public ComGraspEngine(ComGraspEngineOptions options = null)
        {
            CheckAbi();
            if (options == null) options = new ComGraspEngineOptions();
            CgEngineConfig cfg;
            ComGraspNative.cg_engine_config_init_sized(&cfg, (UIntPtr)sizeof(CgEngineConfig));
            cfg.CoordinateSystem = options.Coordinates;
            cfg.EnableFk = options.EnableFk ? 1u : 0u;
            if (options.RingCapacity.HasValue) cfg.RingCapacity = options.RingCapacity.Value;
            if (options.MaxStreams.HasValue) cfg.MaxStreams = options.MaxStreams.Value;
            // An older library's init leaves StructSize short of the fields it does not know.
            if (options.PublishName != null
                && cfg.StructSize < (uint)Marshal.OffsetOf(typeof(CgEngineConfig), "PublishName") + (uint)IntPtr.Size)
                throw new InvalidOperationException(
                    "comgrasp: the loaded library predates cg_engine_config.publish_name (library 0.2)");
            bool runtime = options.StepBackend.HasValue || options.DecoderBackend.HasValue || options.StepThreads.HasValue
                || options.DecoderThreads.HasValue || options.DecodeGroup.HasValue || options.Overlap.HasValue
                || options.MaxIsa.HasValue;
            if (runtime && cfg.StructSize < (uint)Marshal.OffsetOf(typeof(CgEngineConfig), "Scheduling"))
                throw new InvalidOperationException(
                    "comgrasp: the loaded library predates cg_engine_config's runtime options (library 0.3)");
            if ((options.Scheduling.HasValue || options.SchedulerThreads.HasValue) && cfg.StructSize < sizeof(CgEngineConfig))
                throw new InvalidOperationException(
                    "comgrasp: the loaded library predates cg_engine_config.scheduling (library 0.4)");
            if (options.StepBackend.HasValue) cfg.StepBackend = options.StepBackend.Value;
            if (options.DecoderBackend.HasValue) cfg.DecoderBackend = options.DecoderBackend.Value;
            if (options.StepThreads.HasValue) cfg.StepThreads = options.StepThreads.Value;
            if (options.DecoderThreads.HasValue) cfg.DecoderThreads = options.DecoderThreads.Value;
            if (options.DecodeGroup.HasValue) cfg.DecodeGroup = options.DecodeGroup.Value;
            if (options.Overlap.HasValue) cfg.Overlap = options.Overlap.Value;
            if (options.MaxIsa.HasValue) cfg.MaxIsa = options.MaxIsa.Value;
            if (options.Scheduling.HasValue) cfg.Scheduling = options.Scheduling.Value;
            if (options.SchedulerThreads.HasValue) cfg.SchedulerThreads = options.SchedulerThreads.Value;
            byte[] path = options.BundlePath == null ? null : ComGraspNative.NulTerminated(options.BundlePath);
            byte[] publish = options.PublishName == null ? null : ComGraspNative.NulTerminated(options.PublishName);
            IntPtr h = IntPtr.Zero;
            // Both strings are pinned only for the call (the library copies what it keeps).
            fixed (byte* p = path)
            fixed (byte* n = publish)
            {
                cfg.BundlePath = (IntPtr)p;
                cfg.PublishName = (IntPtr)n;
                ComGraspException.Check("cg_engine_create", ComGraspNative.cg_engine_create(&cfg, &h));
            }
            handle = h;
        }

        /// <summary>Starts generating motion for <paramref name="text"/> on a worker thread and
        /// returns at once. null text gives ErrNullPointer; empty or blank text ErrInvalidArgument.</summary>
        public ComGraspStream Start(string text, ComGraspStreamOptions options = default(ComGraspStreamOptions))
        {
            return Start(text == null ? null : Encoding.UTF8.GetBytes(text), options);
        }

        /// <summary>Starts a stream from raw UTF-8 bytes (invalid UTF-8 gives ErrInvalidUtf8).</summary>
        public ComGraspStream Start(byte[] utf8, ComGraspStreamOptions options = default(ComGraspStreamOptions))
        {
            CgStreamConfig cfg;
            ComGraspNative.cg_stream_config_init_sized(&cfg, (UIntPtr)sizeof(CgStreamConfig));
            if (options.Seed.HasValue) { cfg.Seed = options.Seed.Value; cfg.UseDefaults &= ~CgStreamConfig.UseDefaultSeed; }
            if (options.Temperature.HasValue) { cfg.Temperature = options.Temperature.Value; cfg.UseDefaults &= ~CgStreamConfig.UseDefaultTemperature; }
            if (options.TopK.HasValue) { cfg.TopK = options.TopK.Value; cfg.UseDefaults &= ~CgStreamConfig.UseDefaultTopK; }
            if (options.MinLen.HasValue) { cfg.MinLen = options.MinLen.Value; cfg.UseDefaults &= ~CgStreamConfig.UseDefaultMinLen; }
            if (options.MaxLen.HasValue) { cfg.MaxLen = options.MaxLen.Value; cfg.UseDefaults &= ~CgStreamConfig.UseDefaultMaxLen; }
            if (options.Guidance.HasValue) { cfg.Guidance = options.Guidance.Value; cfg.UseDefaults &= ~CgStreamConfig.UseDefaultGuidance; }
            if (options.RawOutput) { cfg.Flags |= CgStreamConfig.FlagRawOutput; }
            if (options.NoGraspPlacement) { cfg.Flags |= CgStreamConfig.FlagNoGraspPlacement; }
            if (options.FreeFeet) { cfg.Flags |= CgStreamConfig.FlagFreeFeet; }
            if (options.CharacterPosition.HasValue)
            {
                cfg.Anchor |= CgStreamConfig.AnchorCharacter;
                CgVec3 p = options.CharacterPosition.Value;
                CgQuat q = options.CharacterRotation ?? new CgQuat(0, 0, 0, 1);
                cfg.CharacterPosition[0] = p.X; cfg.CharacterPosition[1] = p.Y; cfg.CharacterPosition[2] = p.Z;
                cfg.CharacterRotation[0] = q.X; cfg.CharacterRotation[1] = q.Y; cfg.CharacterRotation[2] = q.Z; cfg.CharacterRotation[3] = q.W;
            }
            if (options.ObjectPosition.HasValue)
            {
                cfg.Anchor |= CgStreamConfig.AnchorObject;
                CgVec3 p = options.ObjectPosition.Value;
                CgQuat q = options.ObjectRotation ?? new CgQuat(0, 0, 0, 1);
                cfg.ObjectPosition[0] = p.X; cfg.ObjectPosition[1] = p.Y; cfg.ObjectPosition[2] = p.Z;
                cfg.ObjectRotation[0] = q.X; cfg.ObjectRotation[1] = q.Y; cfg.ObjectRotation[2] = q.Z; cfg.ObjectRotation[3] = q.W;
            }
            if (options.PlaceCharacter) { cfg.Anchor |= CgStreamConfig.AnchorPlaceCharacter; }
            if (options.ContinueFrom.HasValue) { cfg.ContinueFrom = options.ContinueFrom.Value; }
            IntPtr s = IntPtr.Zero;
            // `fixed` on an empty array gives NULL, which the library reads as a missing
            // text: pin a one-byte buffer instead so "" is reported as empty text.
            byte[] buf = utf8 != null && utf8.Length == 0 ? EmptyText : utf8;
            fixed (byte* p = buf)
            {
                int len = utf8 == null ? 0 : utf8.Length;
                ComGraspException.Check("cg_start", ComGraspNative.cg_start_utf8(Handle, p, (UIntPtr)len, &cfg, &s));
            }
            return new ComGraspStream(s);
        }

        /// <summary>Writes frames polled from this engine as BVH (cg_engine_write_bvh): the body
        /// to bodyPath and, unless null, the object's track to objectPath.</summary>
        public void WriteBvh(CgFrame[] frames, string bodyPath, string objectPath = null)
        {
            if (frames == null) throw new ArgumentNullException("frames");
            byte[] body = bodyPath == null ? null : ComGraspNative.NulTerminated(bodyPath);
            byte[] obj = objectPath == null ? null : ComGraspNative.NulTerminated(objectPath);
            fixed (CgFrame* f = frames)
            fixed (byte* b = body)
            fixed (byte* o = obj)
                ComGraspException.Check("cg_engine_write_bvh",
                    ComGraspNative.cg_engine_write_bvh(Handle, f, (UIntPtr)frames.Length, b, o));
        }

        /// <summary>Streams of this engine alive (started and not yet disposed).</summary>
        public uint StreamCount
        {
            get
            {
                uint n;
                ComGraspException.Check("cg_engine_stream_count", ComGraspNative.cg_engine_stream_count(Handle, &n));
                return n;
            }
        }

        /// <summary>Counters of the shared-memory publisher; throws ErrWrongState when the engine
        /// was created without a PublishName.</summary>
        public CgPublisherStats PublisherStats
        {
            get
            {
                CgPublisherStats s;
                ComGraspException.Check("cg_engine_publisher_stats", ComGraspNative.cg_engine_publisher_stats(Handle, &s));
                return s;
            }
        }

        /// <summary>The cg_engine* handle (for ComGraspNative calls).</summary>
        public IntPtr Handle
        {
            get
            {
                if (handle == IntPtr.Zero) throw new ObjectDisposedException("ComGraspEngine");
                return handle;
            }
        }

        public void Dispose()
        {
            Release();
            GC.SuppressFinalize(this);
        }

        ~ComGraspEngine() { Release(); }

        void Release()
        {
            IntPtr h = handle;
            handle = IntPtr.Zero;
            if (h != IntPtr.Zero) ComGraspNative.cg_engine_destroy(h);
        }

        static readonly byte[] EmptyText = new byte[1];
    }

    /// <summary>One generation (cg_stream). Poll it once per frame/tick into a reused CgFrame;
    /// Dispose stops the worker and frees the stream.</summary>
    public sealed unsafe class ComGraspStream : IDisposable
    {
        IntPtr handle;
        readonly ulong id;

        internal ComGraspStream(IntPtr h)
        {
            handle = h;
            ulong v;
            ComGraspException.Check("cg_stream_id", ComGraspNative.cg_stream_id(h, &v));
            id = v;
        }

        /// <summary>The stream's id (unique per engine, from 1); frames carry it as StreamId.</summary>
        public ulong Id { get { return id; } }

        /// <summary>The catalogue object the frames pose (its name, index, and whether the prompt
        /// named it); throws ComGraspException on a disposed stream.</summary>
        public CgStreamInfo Info
        {
            get
            {
                CgStreamInfo info;
                ComGraspException.Check("cg_stream_get_info", ComGraspNative.cg_stream_get_info(handle, &info));
                return info;
            }
        }

        /// <summary>Ok (a frame was written to <paramref name="frame"/>), Pending (nothing yet),
        /// End (every frame delivered) or Cancelled. Never blocks; allocates nothing unless it
        /// throws ComGraspException (the worker's error, e.g. ErrInference).</summary>
        public CgStatus Poll(ref CgFrame frame)
        {
            fixed (CgFrame* p = &frame)
                return ComGraspException.Check("cg_poll_frame", ComGraspNative.cg_poll_frame(Handle, p));
        }

        /// <summary>Like Poll, but waits up to <paramref name="timeoutMs"/> for a frame
        /// (Pending only on timeout). For a consumer thread; never on a game's main thread.</summary>
        public CgStatus Wait(ref CgFrame frame, uint timeoutMs)
        {
            fixed (CgFrame* p = &frame)
                return ComGraspException.Check("cg_stream_wait", ComGraspNative.cg_stream_wait(Handle, timeoutMs, p));
        }

        /// <summary>Poll without exceptions: the raw status, errors included.</summary>
        public CgStatus PollStatus(ref CgFrame frame)
        {
            fixed (CgFrame* p = &frame)
                return ComGraspNative.cg_poll_frame(Handle, p);
        }

        /// <summary>Stops generation within one generator call (~8 ms, default bundle); Poll then returns Cancelled.
        /// Any thread, also while another thread is in Poll/Wait. Idempotent.</summary>
        public void Cancel()
        {
            ComGraspException.Check("cg_cancel", ComGraspNative.cg_cancel(Handle));
        }

        /// <summary>The cg_stream* handle (for ComGraspNative calls).</summary>
        public IntPtr Handle
        {
            get
            {
                if (handle == IntPtr.Zero) throw new ObjectDisposedException("ComGraspStream");
                return handle;
            }
        }

        public void Dispose()
        {
            Release();
            GC.SuppressFinalize(this);
        }

        ~ComGraspStream() { Release(); }

        void Release()
        {
            IntPtr h = handle;
            handle = IntPtr.Zero;
            if (h != IntPtr.Zero) ComGraspNative.cg_stream_destroy(h);
        }
    }

    /// <summary>A shared-memory subscriber (cg_subscriber): receives the frames and stream events
    /// an engine publishes under a name (its PublishName), in this or another process. Works
    /// before the publisher exists and across its restarts; frames arrive from opening on (no
    /// history). Receiving never blocks and allocates nothing: call TryReceive in a loop once
    /// per Update(). One thread at a time; Dispose closes it.</summary>
    public sealed unsafe class ComGraspSubscriber : IDisposable
    {
        IntPtr handle;

        /// <summary>Opens a subscriber on <paramref name="name"/> keeping up to
        /// <paramref name="bufferFrames"/> (1..256) unread frames; beyond that the oldest are
        /// overwritten and counted in Stats.FramesDropped. Errors: ErrInvalidArgument (bad name
        /// or buffer), ErrNullPointer (null name), ErrLimit (8 subscribers already), ErrShm.</summary>
        public ComGraspSubscriber(string name, uint bufferFrames = ComGraspNative.MaxSubscriberBuffer)
        {
            CgSubscriberConfig cfg;
            ComGraspException.Check("cg_subscriber_config_init", ComGraspNative.cg_subscriber_config_init(&cfg));
            cfg.BufferFrames = bufferFrames;
            byte[] n = name == null ? null : ComGraspNative.NulTerminated(name);
            IntPtr h = IntPtr.Zero;
            fixed (byte* p = n)
                ComGraspException.Check("cg_subscriber_open", ComGraspNative.cg_subscriber_open(p, &cfg, &h));
            handle = h;
        }

        /// <summary>Same as the constructor.</summary>
        public static ComGraspSubscriber Open(string name, uint bufferFrames = ComGraspNative.MaxSubscriberBuffer)
        {
            return new ComGraspSubscriber(name, bufferFrames);
        }

        /// <summary>Copies the oldest unread frame into <paramref name="frame"/> and returns true, or
        /// returns false when there is none (frame untouched). Frames of all the publisher's
        /// streams arrive interleaved; tell them apart by StreamId. Never blocks; allocates
        /// nothing unless it throws.</summary>
        public bool TryReceive(ref CgFrame frame)
        {
            fixed (CgFrame* p = &frame)
                return ComGraspException.Check("cg_subscriber_receive", ComGraspNative.cg_subscriber_receive(Handle, p)) == CgStatus.Ok;
        }

        /// <summary>Like TryReceive, for the stream events (a separate queue: a stream's Ended event
        /// may arrive before its last frames). The prompt is <c>ev.GetText()</c>.</summary>
        public bool TryReceiveEvent(ref CgStreamEvent ev)
        {
            fixed (CgStreamEvent* p = &ev)
                return ComGraspException.Check("cg_subscriber_receive_event", ComGraspNative.cg_subscriber_receive_event(Handle, p)) == CgStatus.Ok;
        }

        /// <summary>The prompt of <paramref name="ev"/> as a string (see CgStreamEvent.GetText).</summary>
        public static string EventText(ref CgStreamEvent ev) { return ev.GetText(); }

        /// <summary>Counters since opening (received, dropped, publishers connected).</summary>
        public CgSubscriberStats Stats
        {
            get
            {
                CgSubscriberStats s;
                ComGraspException.Check("cg_subscriber_get_stats", ComGraspNative.cg_subscriber_get_stats(Handle, &s));
                return s;
            }
        }

        /// <summary>The cg_subscriber* handle (for ComGraspNative calls).</summary>
        public IntPtr Handle
        {
            get
            {
                if (handle == IntPtr.Zero) throw new ObjectDisposedException("ComGraspSubscriber");
                return handle;
            }
        }

        /// <summary>Closes the subscriber (cg_subscriber_close); twice is fine.</summary>
        public void Dispose()
        {
            Release();
            GC.SuppressFinalize(this);
        }

        ~ComGraspSubscriber() { Release(); }

        void Release()
        {
            IntPtr h = handle;
            handle = IntPtr.Zero;
            if (h != IntPtr.Zero) ComGraspNative.cg_subscriber_close(h);
        }
    }

    /// <summary>A host bone for <see cref="ComGraspRetargeter"/>: name, parent index (-1: root),
    /// rest translation and rotation (x, y, z, w) relative to the parent, in the engine's
    /// coordinate system and units.</summary>
    public struct ComGraspBone
    {
        public string Name;
        public int Parent;
        public float[] RestTranslation;
        public float[] RestRotation;
    }

    /// <summary>The engine's frames on a host skeleton (cg_retargeter; docs/retargeting.md).
    /// Retarget() fills a caller-owned CgBonePose[] (one per bone, in the order given) and
    /// allocates nothing. Dispose() frees it.</summary>
    public sealed unsafe class ComGraspRetargeter : IDisposable
    {
        IntPtr handle;

        /// <summary>Bones, as given.</summary>
        public int BoneCount { get; private set; }

        /// <summary>With a ready map (entries whose bone the skeleton lacks are skipped).</summary>
        public ComGraspRetargeter(ComGraspEngine engine, ComGraspBone[] bones, CgBuiltinMap map)
            : this(engine, bones, null, map) { }

        /// <summary>With the host's own map: (SMPL-X joint, bone name) pairs.</summary>
        public ComGraspRetargeter(ComGraspEngine engine, ComGraspBone[] bones, KeyValuePair<string, string>[] map)
            : this(engine, bones, map, (CgBuiltinMap)0) { }

        ComGraspRetargeter(ComGraspEngine engine, ComGraspBone[] bones, KeyValuePair<string, string>[] map, CgBuiltinMap builtin)
        {
            var strings = new List<IntPtr>();
            try
            {
                var descs = new CgBoneDesc[Math.Max(1, bones.Length)];
                for (int i = 0; i < bones.Length; i++)
                {
                    var d = new CgBoneDesc { Name = Utf8(bones[i].Name, strings), Parent = bones[i].Parent };
                    for (int k = 0; k < 3; k++) d.RestTranslation[k] = bones[i].RestTranslation[k];
                    for (int k = 0; k < 4; k++) d.RestRotation[k] = bones[i].RestRotation[k];
                    descs[i] = d;
                }
                IntPtr h;
                fixed (CgBoneDesc* d = descs)
                {
                    if (map == null)
                    {
                        ComGraspException.Check("cg_retargeter_create_builtin", ComGraspNative.cg_retargeter_create_builtin(
                            engine.Handle, d, (UIntPtr)bones.Length, (int)builtin, &h));
                    }
                    else
                    {
                        var entries = new CgBoneMapEntry[Math.Max(1, map.Length)];
                        for (int i = 0; i < map.Length; i++)
                        {
                            entries[i].SmplxJoint = Utf8(map[i].Key, strings);
                            entries[i].Bone = Utf8(map[i].Value, strings);
                        }
                        fixed (CgBoneMapEntry* m = entries)
                            ComGraspException.Check("cg_retargeter_create", ComGraspNative.cg_retargeter_create(
                                engine.Handle, d, (UIntPtr)bones.Length, m, (UIntPtr)map.Length, &h));
                    }
                }
                handle = h;
                BoneCount = bones.Length;
            }
            finally
            {
                foreach (IntPtr p in strings) Marshal.FreeHGlobal(p);
            }
        }

        static IntPtr Utf8(string s, List<IntPtr> owned)
        {
            byte[] b = System.Text.Encoding.UTF8.GetBytes(s ?? "");
            IntPtr p = Marshal.AllocHGlobal(b.Length + 1);
            Marshal.Copy(b, 0, p, b.Length);
            Marshal.WriteByte(p, b.Length, 0);
            owned.Add(p);
            return p;
        }

        /// <summary>A ready map's (SMPL-X joint, bone) pairs.</summary>
        public static KeyValuePair<string, string>[] BuiltinMap(CgBuiltinMap which)
        {
            UIntPtr n;
            ComGraspException.Check("cg_builtin_map_size", ComGraspNative.cg_builtin_map_size((int)which, &n));
            var r = new KeyValuePair<string, string>[(int)n];
            for (int i = 0; i < r.Length; i++)
            {
                IntPtr j, b;
                ComGraspException.Check("cg_builtin_map_entry", ComGraspNative.cg_builtin_map_entry((int)which, (UIntPtr)i, &j, &b));
                r[i] = new KeyValuePair<string, string>(Marshal.PtrToStringAnsi(j), Marshal.PtrToStringAnsi(b));
            }
            return r;
        }

        /// <summary>Poses every bone for one frame into poses (length BoneCount) and the object
        /// into obj. No allocation.</summary>
        public void Retarget(ref CgFrame frame, CgBonePose[] poses, out CgRetargetObject obj)
        {
            if (poses == null || poses.Length != BoneCount)
                throw new ArgumentException("poses must have BoneCount (" + BoneCount + ") entries");
            CgRetargetObject o;
            fixed (CgFrame* f = &frame)
            fixed (CgBonePose* p = poses)
                ComGraspException.Check("cg_retarget_frame", ComGraspNative.cg_retarget_frame(Handle, f, p, (UIntPtr)poses.Length, &o));
            obj = o;
        }

        /// <summary>The cg_retargeter* handle.</summary>
        public IntPtr Handle
        {
            get
            {
                if (handle == IntPtr.Zero) throw new ObjectDisposedException("ComGraspRetargeter");
                return handle;
            }
        }

        public void Dispose()
        {
            IntPtr h = handle;
            handle = IntPtr.Zero;
            if (h != IntPtr.Zero) ComGraspNative.cg_retargeter_destroy(h);
            GC.SuppressFinalize(this);
        }

        ~ComGraspRetargeter() { Dispose(); }
    }
}
