// ComGraspModule.h: the plugin's module. Owns the ComGrasp engines (one per bundle path,
// created on first use in Unreal coordinates and shared by every UComGraspComponent), so a
// model bundle is loaded once, not once per component.
#pragma once

#include "CoreMinimal.h"
#include "HAL/CriticalSection.h"
#include "Modules/ModuleInterface.h"

THIRD_PARTY_INCLUDES_START
#include "comgrasp.h"
THIRD_PARTY_INCLUDES_END

DECLARE_LOG_CATEGORY_EXTERN(LogComGrasp, Log, All);

class COMGRASP_API FComGraspModule : public IModuleInterface
{
public:
	static FComGraspModule& Get();

	/** The shared engine of a bundle directory (empty: the bundle embedded in the library),
	 * frames in CG_COORDS_UNREAL (centimetres, z up, left-handed). Null on failure, with
	 * the library's message in OutError. Any thread. */
	cg_engine* AcquireEngine(const FString& BundlePath, FString& OutError);

	virtual void StartupModule() override;
	/** Destroys the engines; streams still running are cancelled by the library (their
	 * handles stay valid until their components destroy them). */
	virtual void ShutdownModule() override;

private:
	FCriticalSection Lock;
	TMap<FString, cg_engine*> Engines;
};
