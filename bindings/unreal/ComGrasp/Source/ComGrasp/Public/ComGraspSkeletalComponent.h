// ComGraspSkeletalComponent.h: poses a character's USkeletalMeshComponent from the engine's
// retargeted frames (body, fingers) and moves the grasped object, each tick.
//
// The engine-facing work (stream, real-time pacing, retargeting, chaining) is
// comgrasp_unreal::PoseDriver (ComGraspPoseDriver.h, plain C++ tested in the engine's CI);
// this component only reads the mesh's reference skeleton and writes bone transforms:
// into a hidden UPoseableMeshComponent with the same mesh, which the character's mesh
// follows as its leader pose component. The UE5 Mannequin map is the default.
//
// NOT COMPILED AGAINST UNREAL HERE (no Unreal Engine in CI). Written for UE 5.1+ (the
// SkinnedAsset and LeaderPose names); on 5.0 use GetSkeletalMesh / SetSkeletalMesh /
// SetMasterPoseComponent instead.
#pragma once

#include "Components/ActorComponent.h"
#include "CoreMinimal.h"

THIRD_PARTY_INCLUDES_START
#include "comgrasp.h"
// Complete here (not forward-declared), so the generated code can destroy the unique_ptr.
#include "ComGraspPoseDriver.h"
THIRD_PARTY_INCLUDES_END

#include <memory>

#include "ComGraspSkeletalComponent.generated.h"

class UPoseableMeshComponent;
class USkeletalMeshComponent;

UENUM(BlueprintType)
enum class EComGraspSkeletonMap : uint8
{
	UE5Mannequin = 2 UMETA(DisplayName = "UE5 Mannequin"),
	Mixamo = 3 UMETA(DisplayName = "Mixamo"),
	UnityHumanoidNames = 1 UMETA(DisplayName = "Unity HumanBodyBones names"),
};

UCLASS(ClassGroup = (Animation), meta = (BlueprintSpawnableComponent))
class COMGRASP_API UComGraspSkeletalComponent : public UActorComponent
{
	GENERATED_BODY()

public:
	UComGraspSkeletalComponent();
	virtual ~UComGraspSkeletalComponent() override;

	/** What the character does, e.g. "A woman drinks from the mug". */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	FString Prompt = TEXT("A woman drinks from the mug");

	/** Model bundle directory; empty: the default embedded in the library. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	FString BundlePath;

	/** The character's mesh; empty: the first USkeletalMeshComponent of the owner. Its
	 * reference pose is the rest pose the motion is retargeted from. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	TObjectPtr<USkeletalMeshComponent> TargetMesh;

	/** Which bone names the mesh's skeleton uses. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	EComGraspSkeletonMap SkeletonMap = EComGraspSkeletonMap::UE5Mannequin;

	/** The object the character grasps (moved with the motion); optional. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	TObjectPtr<AActor> GraspedObject;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	bool bStartOnBeginPlay = true;

	/** On: frames at their time stamps; off: the newest generated frame each tick. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	bool bPlayInRealTime = true;

	/** StartMotion continues from where the last motion ended (pose, place, object). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "ComGrasp")
	bool bChain = true;

	/** Starts a motion for NewPrompt (stopping one that plays). False on error (logged). */
	UFUNCTION(BlueprintCallable, Category = "ComGrasp")
	bool StartMotion(const FString& NewPrompt);

	/** Stops the motion; the character keeps its last pose. */
	UFUNCTION(BlueprintCallable, Category = "ComGrasp")
	void CancelMotion();

	UFUNCTION(BlueprintPure, Category = "ComGrasp")
	bool IsPlaying() const;

	virtual void TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction) override;

protected:
	virtual void BeginPlay() override;
	virtual void EndPlay(const EEndPlayReason::Type EndPlayReason) override;

private:
	bool Setup();
	void ApplyPose();

	std::unique_ptr<comgrasp_unreal::PoseDriver> Driver;
	UPROPERTY(Transient)
	TObjectPtr<UPoseableMeshComponent> Poseable;
	TArray<FName> BoneNames;
};
