// ComGraspComponent.h: streams a generated grasp motion into an actor.
//
// On BeginPlay it starts a stream for Prompt; every tick it polls the frames that are due
// (never blocking, into one preallocated cg_frame) and exposes the latest pose: the root
// (pelvis) and object transforms as FTransform, contacts, and the raw frame for C++ (body
// and finger local rotations, wrist vectors, joint positions). EndPlay cancels the stream.
//
// Units and axes: the engine runs in CG_COORDS_UNREAL (centimetres, z up, left-handed), so
// positions are FVector(x, y, z) and rotations FQuat(x, y, z, w) unchanged. Transforms are
// in the motion's own space; put them in the world with the owner's transform
// (GetWorldRootTransform / GetWorldObjectTransform).
#pragma once

#include "Components/ActorComponent.h"
#include "CoreMinimal.h"

THIRD_PARTY_INCLUDES_START
#include "comgrasp.h"
THIRD_PARTY_INCLUDES_END

#include "ComGraspComponent.generated.h"

DECLARE_DYNAMIC_MULTICAST_DELEGATE_OneParam(FComGraspStreamEnded, bool, bCancelled);

UCLASS(ClassGroup = (Animation), meta = (BlueprintSpawnableComponent))
class COMGRASP_API UComGraspComponent : public UActorComponent
{
	GENERATED_BODY()

public:
	UComGraspComponent();

	/** What to generate, e.g. "A woman drinks from the mug" (UTF-8, at most 4096 bytes). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	FString Prompt = TEXT("A woman drinks from the mug");

	/** Model bundle directory, absolute or relative to the project; empty: the bundle
	 * embedded in the library. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	FString BundlePath;

	/** Start a stream for Prompt on BeginPlay. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	bool bStartOnBeginPlay = true;

	/** On: play at the motion's frame rate (each tick takes the frames whose time has come).
	 * Off: each tick takes every frame available, so the pose is the newest generated one. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	bool bPlayInRealTime = true;

	/** Sampling seed; negative: the bundle's default. Same seed + prompt + bundle = same motion. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	int32 Seed = -1;

	/** Pelvis transform of the latest frame (motion space, cm). */
	UPROPERTY(BlueprintReadOnly, Category = "ComGrasp|Pose")
	FTransform RootTransform;

	/** Object transform of the latest frame (motion space, cm). */
	UPROPERTY(BlueprintReadOnly, Category = "ComGrasp|Pose")
	FTransform ObjectTransform;

	/** Centre of the object's bounding box (motion space, cm). */
	UPROPERTY(BlueprintReadOnly, Category = "ComGrasp|Pose")
	FVector ObjectCentre = FVector::ZeroVector;

	/** Contact probability of the left and right hand, 0..1. */
	UPROPERTY(BlueprintReadOnly, Category = "ComGrasp|Pose")
	float LeftContactProbability = 0.f;
	UPROPERTY(BlueprintReadOnly, Category = "ComGrasp|Pose")
	float RightContactProbability = 0.f;

	/** Index of the latest frame in its stream; -1 before the first frame. */
	UPROPERTY(BlueprintReadOnly, Category = "ComGrasp|Pose")
	int64 FrameIndex = -1;

	/** True once the stream ended (every frame taken), was cancelled, or failed. */
	UPROPERTY(BlueprintReadOnly, Category = "ComGrasp")
	bool bFinished = false;

	/** Broadcast when the stream ends (false) or is cancelled / fails (true). */
	UPROPERTY(BlueprintAssignable, Category = "ComGrasp")
	FComGraspStreamEnded OnStreamEnded;

	/** Cancels the current stream (if any) and starts one for NewPrompt. False on error
	 * (logged to LogComGrasp with the library's message). */
	UFUNCTION(BlueprintCallable, Category = "ComGrasp")
	bool StartStream(const FString& NewPrompt);

	/** Stops and frees the current stream. */
	UFUNCTION(BlueprintCallable, Category = "ComGrasp")
	void CancelStream();

	/** Local rotation of SMPL-X body joint Index + 1 (Index 0..20) in the latest frame. */
	UFUNCTION(BlueprintPure, Category = "ComGrasp|Pose")
	FRotator GetBodyJointRotation(int32 Index) const;

	UFUNCTION(BlueprintPure, Category = "ComGrasp|Pose")
	FTransform GetWorldRootTransform() const;

	UFUNCTION(BlueprintPure, Category = "ComGrasp|Pose")
	FTransform GetWorldObjectTransform() const;

	/** The latest frame as the library wrote it (valid when FrameIndex >= 0). */
	const cg_frame& GetFrame() const { return Frame; }

	virtual void TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction) override;

protected:
	virtual void BeginPlay() override;
	virtual void EndPlay(const EEndPlayReason::Type EndPlayReason) override;
	/** Frees a stream that EndPlay did not (a component destroyed without playing out). */
	virtual void BeginDestroy() override;

private:
	void ApplyFrame();
	void Finish(cg_status Status);

	cg_stream* Stream = nullptr;
	/** Written by cg_poll_frame; preallocated, so ticking allocates nothing. */
	cg_frame Frame;
	/** Seconds of motion played since the stream started. */
	double PlaybackTime = 0.0;
};
