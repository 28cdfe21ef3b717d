// GraspDemoButtons.cs: on-screen Play / Cancel / Next for the Grasp demo (see README.md).
#if UNITY_5_3_OR_NEWER
using UnityEngine;

namespace ComGrasp.Samples
{
    public sealed class GraspDemoButtons : MonoBehaviour
    {
        public ComGraspAnimator character;
        public string[] prompts = { "A woman drinks from the mug", "She puts the mug down", "She waves" };
        int next;

        void OnGUI()
        {
            if (character == null) return;
            GUILayout.BeginArea(new Rect(10, 10, 320, 200));
            GUILayout.Label(character.Playing ? "playing: " + character.prompt : "idle");
            character.prompt = GUILayout.TextField(character.prompt);
            if (GUILayout.Button("Play")) character.Play();
            if (GUILayout.Button("Cancel")) character.Cancel();
            if (GUILayout.Button("Next prompt (chained)"))
            {
                character.prompt = prompts[next++ % prompts.Length];
                character.Play();
            }
            GUILayout.EndArea();
        }
    }
}
#endif
