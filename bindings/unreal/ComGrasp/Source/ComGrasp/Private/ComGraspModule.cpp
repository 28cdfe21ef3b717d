#include "ComGraspModule.h"

#include "Misc/Paths.h"
#include "Modules/ModuleManager.h"

DEFINE_LOG_CATEGORY(LogComGrasp);

FComGraspModule& FComGraspModule::Get()
{
	return FModuleManager::LoadModuleChecked<FComGraspModule>("ComGrasp");
}

void FComGraspModule::StartupModule()
{
	// A stale library linked against a newer header (or the reverse) must not be used.
	if (cg_abi_version() != CG_ABI_VERSION || cg_frame_size() != sizeof(cg_frame))
	{
		UE_LOG(LogComGrasp, Error, TEXT("libcomgrasp ABI %u / frame size %llu does not match comgrasp.h (ABI %u, %llu bytes)"),
			cg_abi_version(), (unsigned long long)cg_frame_size(), (unsigned)CG_ABI_VERSION, (unsigned long long)sizeof(cg_frame));
	}
	else
	{
		UE_LOG(LogComGrasp, Log, TEXT("ComGrasp engine %s"), UTF8_TO_TCHAR(cg_version_string()));
	}
}

void FComGraspModule::ShutdownModule()
{
	FScopeLock Guard(&Lock);
	for (TPair<FString, cg_engine*>& Pair : Engines)
	{
		cg_engine_destroy(Pair.Value);
	}
	Engines.Empty();
}

cg_engine* FComGraspModule::AcquireEngine(const FString& BundlePath, FString& OutError)
{
	if (cg_abi_version() != CG_ABI_VERSION || cg_frame_size() != sizeof(cg_frame))
	{
		OutError = TEXT("libcomgrasp does not match comgrasp.h (ABI version or frame size)");
		return nullptr;
	}
	// Relative paths are relative to the project folder.
	const FString Key = BundlePath.IsEmpty() ? FString() : FPaths::ConvertRelativePathToFull(FPaths::ProjectDir(), BundlePath);
	FScopeLock Guard(&Lock);
	if (cg_engine** Found = Engines.Find(Key))
	{
		return *Found;
	}
	cg_engine_config Config;
	cg_engine_config_init(&Config);
	Config.coordinate_system = CG_COORDS_UNREAL;
	FTCHARToUTF8 Path(*Key);
	Config.bundle_path = Key.IsEmpty() ? nullptr : Path.Get();
	cg_engine* Engine = nullptr;
	const cg_status Status = cg_engine_create(&Config, &Engine);
	if (Status != CG_OK)
	{
		OutError = FString::Printf(TEXT("cg_engine_create: %s: %s"), UTF8_TO_TCHAR(cg_status_string(Status)), UTF8_TO_TCHAR(cg_last_error()));
		return nullptr;
	}
	Engines.Add(Key, Engine);
	return Engine;
}

IMPLEMENT_MODULE(FComGraspModule, ComGrasp)
