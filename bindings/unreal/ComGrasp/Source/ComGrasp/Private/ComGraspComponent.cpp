#include "ComGraspComponent.h"

#include "ComGraspModule.h"
#include "GameFramework/Actor.h"

namespace
{
FVector ToVector(const float* V)
{
	return FVector(V[0], V[1], V[2]);
}

// CG_COORDS_UNREAL already applied the basis change to every rotation: the quaternion's
// components are used as they are.
FQuat ToQuat(const float* Q)
{
	return FQuat(Q[0], Q[1], Q[2], Q[3]);
}

FString LastError(const TCHAR* Call, cg_status Status)
{
	return FString::Printf(TEXT("%s: %s: %s"), Call, UTF8_TO_TCHAR(cg_status_string(Status)), UTF8_TO_TCHAR(cg_last_error()));
}
}  // namespace

UComGraspComponent::UComGraspComponent()
{
	PrimaryComponentTick.bCanEverTick = true;
	PrimaryComponentTick.bStartWithTickEnabled = true;
	FMemory::Memzero(Frame);
}

void UComGraspComponent::BeginPlay()
{
	Super::BeginPlay();
	if (bStartOnBeginPlay)
	{
		StartStream(Prompt);
	}
}

void UComGraspComponent::EndPlay(const EEndPlayReason::Type EndPlayReason)
{
	CancelStream();
	Super::EndPlay(EndPlayReason);
}

void UComGraspComponent::BeginDestroy()
{
	CancelStream();
	Super::BeginDestroy();
}

bool UComGraspComponent::StartStream(const FString& NewPrompt)
{
	CancelStream();
	Prompt = NewPrompt;
	bFinished = false;
	FrameIndex = -1;
	PlaybackTime = 0.0;

	FString Error;
	cg_engine* Engine = FComGraspModule::Get().AcquireEngine(BundlePath, Error);
	if (!Engine)
	{
		UE_LOG(LogComGrasp, Error, TEXT("%s"), *Error);
		bFinished = true;
		return false;
	}
	cg_stream_config Config;
	cg_stream_config_init(&Config);
	if (Seed >= 0)
	{
		Config.seed = static_cast<uint64_t>(Seed);
		Config.use_defaults &= ~static_cast<uint32_t>(CG_USE_DEFAULT_SEED);
	}
	FTCHARToUTF8 Text(*Prompt);
	const cg_status Status = cg_start_utf8(Engine, reinterpret_cast<const uint8_t*>(Text.Get()), Text.Length(), &Config, &Stream);
	if (Status != CG_OK)
	{
		UE_LOG(LogComGrasp, Error, TEXT("%s (prompt \"%s\")"), *LastError(TEXT("cg_start"), Status), *Prompt);
		Stream = nullptr;
		bFinished = true;
		return false;
	}
	return true;
}

void UComGraspComponent::CancelStream()
{
	if (Stream)
	{
		cg_cancel(Stream);
		cg_stream_destroy(Stream);  // joins the worker: at most one generator call (~8 ms, default bundle)
		Stream = nullptr;
	}
}

void UComGraspComponent::TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction)
{
	Super::TickComponent(DeltaTime, TickType, ThisTickFunction);
	if (!Stream)
	{
		return;
	}
	PlaybackTime += DeltaTime;
	int32 Taken = 0;
	for (;;)
	{
		// In real time, wait once the newest frame taken is not yet due.
		if (bPlayInRealTime && (FrameIndex >= 0 || Taken > 0) && Frame.time_s >= PlaybackTime)
		{
			break;
		}
		// Never blocks, never allocates; writes Frame only on CG_OK.
		const cg_status Status = cg_poll_frame(Stream, &Frame);
		if (Status == CG_OK)
		{
			++Taken;
			continue;
		}
		if (Status != CG_PENDING)
		{
			Finish(Status);  // CG_END, CG_CANCELLED or an error
		}
		break;
	}
	if (Taken > 0)
	{
		ApplyFrame();
	}
}

void UComGraspComponent::ApplyFrame()
{
	FrameIndex = static_cast<int64>(Frame.frame_index);
	RootTransform = FTransform(ToQuat(Frame.root_rotation), ToVector(Frame.root_translation));
	ObjectTransform = FTransform(ToQuat(Frame.object_rotation), ToVector(Frame.object_translation));
	ObjectCentre = ToVector(Frame.object_centre);
	LeftContactProbability = Frame.contact_probability[0];
	RightContactProbability = Frame.contact_probability[1];
}

void UComGraspComponent::Finish(cg_status Status)
{
	if (Status < 0)
	{
		UE_LOG(LogComGrasp, Error, TEXT("%s"), *LastError(TEXT("cg_poll_frame"), Status));
	}
	cg_stream_destroy(Stream);
	Stream = nullptr;
	bFinished = true;
	OnStreamEnded.Broadcast(Status != CG_END);
}

FRotator UComGraspComponent::GetBodyJointRotation(int32 Index) const
{
	if (Index < 0 || Index >= CG_BODY_JOINTS || FrameIndex < 0)
	{
		return FRotator::ZeroRotator;
	}
	return ToQuat(Frame.body_rotations[Index]).Rotator();
}

FTransform UComGraspComponent::GetWorldRootTransform() const
{
	const AActor* Owner = GetOwner();
	return Owner ? RootTransform * Owner->GetActorTransform() : RootTransform;
}

FTransform UComGraspComponent::GetWorldObjectTransform() const
{
	const AActor* Owner = GetOwner();
	return Owner ? ObjectTransform * Owner->GetActorTransform() : ObjectTransform;
}
