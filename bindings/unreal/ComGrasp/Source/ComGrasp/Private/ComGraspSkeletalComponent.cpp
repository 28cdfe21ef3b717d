#include "ComGraspSkeletalComponent.h"

#include "ComGraspModule.h"
#include "ComGraspPoseDriver.h"
#include "Components/PoseableMeshComponent.h"
#include "Components/SkeletalMeshComponent.h"
#include "Engine/SkeletalMesh.h"
#include "GameFramework/Actor.h"

using comgrasp_unreal::BoneRest;
using comgrasp_unreal::PoseDriver;
using comgrasp_unreal::TickResult;

UComGraspSkeletalComponent::UComGraspSkeletalComponent()
{
	PrimaryComponentTick.bCanEverTick = true;
}

UComGraspSkeletalComponent::~UComGraspSkeletalComponent() = default;

void UComGraspSkeletalComponent::BeginPlay()
{
	Super::BeginPlay();
	if (Setup() && bStartOnBeginPlay)
	{
		StartMotion(Prompt);
	}
}

void UComGraspSkeletalComponent::EndPlay(const EEndPlayReason::Type EndPlayReason)
{
	Driver.reset();  // cancels the stream
	Super::EndPlay(EndPlayReason);
}

bool UComGraspSkeletalComponent::Setup()
{
	AActor* Owner = GetOwner();
	if (!TargetMesh && Owner)
	{
		TargetMesh = Owner->FindComponentByClass<USkeletalMeshComponent>();
	}
	if (!TargetMesh || !TargetMesh->GetSkinnedAsset())
	{
		UE_LOG(LogComGrasp, Error, TEXT("ComGrasp: no skeletal mesh to drive"));
		return false;
	}
	FString Error;
	cg_engine* Engine = FComGraspModule::Get().AcquireEngine(BundlePath, Error);
	if (!Engine)
	{
		UE_LOG(LogComGrasp, Error, TEXT("%s"), *Error);
		return false;
	}
	// The rest pose: the mesh's reference pose, parent-relative (centimetres, z up: the
	// engine's CG_COORDS_UNREAL), the root's relative to the actor (the mesh is usually
	// turned -90 degrees in its actor), so the motion's space is the actor's.
	const FReferenceSkeleton& Ref = TargetMesh->GetSkinnedAsset()->GetRefSkeleton();
	const TArray<FTransform>& RefPose = Ref.GetRefBonePose();
	const FTransform MeshInActor = TargetMesh->GetComponentTransform().GetRelativeTransform(Owner->GetActorTransform());
	std::vector<BoneRest> Bones(Ref.GetNum());
	BoneNames.SetNum(Ref.GetNum());
	for (int32 i = 0; i < Ref.GetNum(); ++i)
	{
		BoneNames[i] = Ref.GetBoneName(i);
		Bones[i].name = TCHAR_TO_UTF8(*BoneNames[i].ToString());
		Bones[i].parent = Ref.GetParentIndex(i);
		const FTransform Rest = Bones[i].parent < 0 ? RefPose[i] * MeshInActor : RefPose[i];
		const FVector T = Rest.GetTranslation();
		const FQuat Q = Rest.GetRotation().GetNormalized();
		Bones[i].translation[0] = T.X; Bones[i].translation[1] = T.Y; Bones[i].translation[2] = T.Z;
		Bones[i].rotation[0] = Q.X; Bones[i].rotation[1] = Q.Y; Bones[i].rotation[2] = Q.Z; Bones[i].rotation[3] = Q.W;
	}
	Driver = std::make_unique<PoseDriver>(Engine, Bones, static_cast<int32_t>(SkeletonMap));
	if (!Driver->ok())
	{
		UE_LOG(LogComGrasp, Error, TEXT("ComGrasp: %s"), UTF8_TO_TCHAR(Driver->error().c_str()));
		Driver.reset();
		return false;
	}
	// A hidden poseable copy of the mesh is written each frame; the character's mesh follows it.
	Poseable = NewObject<UPoseableMeshComponent>(Owner);
	Poseable->SetSkinnedAssetAndUpdate(TargetMesh->GetSkinnedAsset());
	Poseable->SetupAttachment(TargetMesh);
	Poseable->SetVisibility(false);
	Poseable->RegisterComponent();
	TargetMesh->SetLeaderPoseComponent(Poseable);
	return true;
}

bool UComGraspSkeletalComponent::StartMotion(const FString& NewPrompt)
{
	if (!Driver)
	{
		return false;
	}
	Prompt = NewPrompt;
	cg_stream_config Config;
	cg_stream_config_init(&Config);
	const bool bChained = bChain && Driver->last_ended() != 0;
	if (!bChained)
	{
		// Scene anchoring in the motion's space, which is the actor's: the ground point is
		// the mesh's origin (a Character's actor origin is its capsule's centre), the heading
		// the actor's forward, +X (the engine's unturned character faces -Y: yaw it by 90).
		const FVector Ground = TargetMesh->GetComponentTransform().GetRelativeTransform(GetOwner()->GetActorTransform()).GetTranslation();
		const FQuat Heading = FQuat(FRotator(0.0, 90.0, 0.0));
		Config.anchor |= CG_ANCHOR_CHARACTER;
		Config.character_position[0] = Ground.X; Config.character_position[1] = Ground.Y; Config.character_position[2] = Ground.Z;
		Config.character_rotation[0] = Heading.X; Config.character_rotation[1] = Heading.Y;
		Config.character_rotation[2] = Heading.Z; Config.character_rotation[3] = Heading.W;
	}
	// A grasped object anchors the reach (it must be within arm's reach).
	if (GraspedObject && !bChained)
	{
		const FTransform InActor = GraspedObject->GetActorTransform().GetRelativeTransform(GetOwner()->GetActorTransform());
		const FVector P = InActor.GetTranslation();
		const FQuat Q = InActor.GetRotation();
		Config.anchor |= CG_ANCHOR_OBJECT;
		Config.object_position[0] = P.X; Config.object_position[1] = P.Y; Config.object_position[2] = P.Z;
		Config.object_rotation[0] = Q.X; Config.object_rotation[1] = Q.Y; Config.object_rotation[2] = Q.Z; Config.object_rotation[3] = Q.W;
	}
	if (!Driver->start(std::string(TCHAR_TO_UTF8(*Prompt)), &Config, bChained))
	{
		UE_LOG(LogComGrasp, Error, TEXT("ComGrasp: %s"), UTF8_TO_TCHAR(Driver->error().c_str()));
		return false;
	}
	return true;
}

void UComGraspSkeletalComponent::CancelMotion()
{
	if (Driver)
	{
		Driver->stop();
	}
}

bool UComGraspSkeletalComponent::IsPlaying() const
{
	return Driver && Driver->playing();
}

void UComGraspSkeletalComponent::TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction)
{
	Super::TickComponent(DeltaTime, TickType, ThisTickFunction);
	if (!Driver)
	{
		return;
	}
	const TickResult Result = Driver->tick(DeltaTime, bPlayInRealTime);
	if (Result == TickResult::NewPose)
	{
		ApplyPose();
	}
	else if (Result == TickResult::Failed)
	{
		UE_LOG(LogComGrasp, Error, TEXT("ComGrasp: %s"), UTF8_TO_TCHAR(Driver->error().c_str()));
	}
}

void UComGraspSkeletalComponent::ApplyPose()
{
	const FTransform Actor = GetOwner()->GetActorTransform();
	const std::vector<cg_bone_pose>& Poses = Driver->poses();
	// World transforms, parents first (the reference skeleton's order).
	for (int32 i = 0; i < BoneNames.Num(); ++i)
	{
		const cg_bone_pose& P = Poses[i];
		const FTransform InActor(FQuat(P.world_rotation[0], P.world_rotation[1], P.world_rotation[2], P.world_rotation[3]),
			FVector(P.world_position[0], P.world_position[1], P.world_position[2]));
		Poseable->SetBoneTransformByName(BoneNames[i], InActor * Actor, EBoneSpaces::WorldSpace);
	}
	if (GraspedObject)
	{
		const cg_retarget_object& O = Driver->object();
		const FTransform InActor(FQuat(O.world_rotation[0], O.world_rotation[1], O.world_rotation[2], O.world_rotation[3]),
			FVector(O.world_position[0], O.world_position[1], O.world_position[2]));
		GraspedObject->SetActorTransform(InActor * Actor);
	}
}
