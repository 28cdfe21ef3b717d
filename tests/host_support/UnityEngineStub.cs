// A stub of the few UnityEngine types the Unity package uses (names and signatures as in
// Unity's scripting reference), so tests/csharp_binding.rs can compile
// bindings/unity/Runtime/*.cs with UNITY_5_3_OR_NEWER defined. It checks the package's own
// code (types, calls, unsafe blocks), not Unity's API: the bodies do nothing useful.
using System;

namespace UnityEngine
{
    public class Object { }

    public class Component : Object
    {
        public Transform transform { get { return null; } }
        public T GetComponent<T>() { return default(T); }
    }

    public class Behaviour : Component
    {
        public bool enabled { get; set; }
    }

    public class MonoBehaviour : Behaviour { }

    public class Transform : Component
    {
        public Vector3 position { get; set; }
        public Quaternion rotation { get; set; }
        public Vector3 InverseTransformPoint(Vector3 p) { return p; }
        public void SetPositionAndRotation(Vector3 position, Quaternion rotation) { }
    }

    public enum HumanBodyBones { Hips = 0, LastBone = 55 }

    public class Animator : Behaviour
    {
        public bool isHuman { get { return true; } }
        public Transform GetBoneTransform(HumanBodyBones bone) { return null; }
    }

    public struct Vector3
    {
        public float x, y, z;
        public Vector3(float x, float y, float z) { this.x = x; this.y = y; this.z = z; }
        public static Vector3 up { get { return new Vector3(0f, 1f, 0f); } }
    }

    public struct Quaternion
    {
        public float x, y, z, w;
        public Quaternion(float x, float y, float z, float w) { this.x = x; this.y = y; this.z = z; this.w = w; }
        public static Quaternion Inverse(Quaternion q) { return new Quaternion(-q.x, -q.y, -q.z, q.w); }
        public static Quaternion AngleAxis(float angle, Vector3 axis) { return new Quaternion(0f, 0f, 0f, 1f); }
        public static Quaternion operator *(Quaternion a, Quaternion b) { return a; }
    }

    public static class Debug
    {
        public static void LogError(object message, Object context) { }
    }

    public static class Time
    {
        public static float deltaTime { get { return 0f; } }
    }

    public struct Rect
    {
        public Rect(float x, float y, float width, float height) { }
    }

    public static class GUILayout
    {
        public static void BeginArea(Rect area) { }
        public static void EndArea() { }
        public static void Label(string text) { }
        public static string TextField(string text) { return text; }
        public static bool Button(string text) { return false; }
    }

    [AttributeUsage(AttributeTargets.Field)]
    public sealed class TooltipAttribute : Attribute
    {
        public TooltipAttribute(string tooltip) { }
    }

    [AttributeUsage(AttributeTargets.Class)]
    public sealed class AddComponentMenuAttribute : Attribute
    {
        public AddComponentMenuAttribute(string menuName) { }
    }
}
