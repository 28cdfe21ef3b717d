// ComGrasp.Build.cs: links the ComGrasp Engine's static library and adds comgrasp.h.
//
// Where the library is, in order:
//   1. $COMGRASP_ROOT: a prefix made by the engine's `scripts/install.sh PREFIX`
//      (PREFIX/include/comgrasp.h, PREFIX/lib/libcomgrasp.a);
//   2. ThirdParty/comgrasp inside this plugin: include/comgrasp.h and the library in
//      lib/<Platform>/ (Win64, Linux, Mac) or lib/ (what `scripts/install.sh
//      Plugins/ComGrasp/ThirdParty/comgrasp` writes).
// The system libraries are what `cargo rustc --lib --crate-type staticlib -- --print
// native-static-libs` prints for each platform. Not built in the engine's CI (no Unreal
// there): see README.md.
using System;
using System.IO;
using UnrealBuildTool;

public class ComGrasp : ModuleRules
{
	public ComGrasp(ReadOnlyTargetRules Target) : base(Target)
	{
		PCHUsage = PCHUsageMode.UseExplicitOrSharedPCHs;
		PublicDependencyModuleNames.AddRange(new string[] { "Core", "CoreUObject", "Engine" });

		string Root = Environment.GetEnvironmentVariable("COMGRASP_ROOT");
		if (string.IsNullOrEmpty(Root))
		{
			Root = Path.GetFullPath(Path.Combine(ModuleDirectory, "..", "..", "ThirdParty", "comgrasp"));
		}
		string IncludeDir = Path.Combine(Root, "include");
		if (!File.Exists(Path.Combine(IncludeDir, "comgrasp.h")))
		{
			throw new BuildException("ComGrasp: comgrasp.h not found in " + IncludeDir + " (see Plugins/ComGrasp/README.md)");
		}
		PublicIncludePaths.Add(IncludeDir);

		bool Windows = Target.Platform == UnrealTargetPlatform.Win64;
		string LibName = Windows ? "comgrasp.lib" : "libcomgrasp.a";
		string Lib = Path.Combine(Root, "lib", Target.Platform.ToString(), LibName);
		if (!File.Exists(Lib))
		{
			Lib = Path.Combine(Root, "lib", LibName);
		}
		if (!File.Exists(Lib))
		{
			throw new BuildException("ComGrasp: " + LibName + " not found in " + Path.Combine(Root, "lib") + " (see Plugins/ComGrasp/README.md)");
		}
		PublicAdditionalLibraries.Add(Lib);

		if (Windows)
		{
			PublicSystemLibraries.AddRange(new string[] { "kernel32.lib", "advapi32.lib", "ntdll.lib", "userenv.lib", "ws2_32.lib", "dbghelp.lib", "bcrypt.lib" });
		}
		else if (Target.Platform == UnrealTargetPlatform.Linux)
		{
			PublicSystemLibraries.AddRange(new string[] { "gcc_s", "util", "rt", "pthread", "m", "dl", "c" });
		}
		else if (Target.Platform == UnrealTargetPlatform.Mac)
		{
			PublicSystemLibraries.AddRange(new string[] { "c", "m" });
		}
		else
		{
			throw new BuildException("ComGrasp: no library for " + Target.Platform);
		}
	}
}
