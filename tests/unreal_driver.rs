//! The Unreal plugin's engine-facing C++ (bindings/unreal/.../ComGraspPoseDriver.h, no Unreal
//! types) compiled as Unreal compiles (C++17, no exceptions, no RTTI, warnings as errors) and
//! run against the real library: bindings/unreal/tests/pose_driver_test.cpp poses a skeleton
//! named as the UE5 Mannequin in Unreal coordinates frame by frame (world positions on the
//! frames' joints within 1 mm), plays in real time and chained, and checks the errors. The
//! Unreal component around it (UComGraspSkeletalComponent) is not compiled here: no Unreal
//! Engine in CI.
#![cfg(target_os = "linux")]

mod host_support;

use std::process::Command;
use std::time::Duration;

use host_support::*;

#[test]
fn unreal_pose_driver_poses_a_mannequin_skeleton() {
    let exe = compile(
        "CXX",
        "c++",
        "-std=c++17",
        &["bindings/unreal/tests/pose_driver_test.cpp", "-Ibindings/unreal/ComGrasp/Source/ComGrasp/Public"],
        "unreal_pose_driver_test",
        &["-fno-exceptions", "-fno-rtti", "-pthread"],
    );
    let stdout = run_ok(Command::new(&exe).arg(tiny()), Duration::from_secs(300));
    assert!(stdout.contains("posed ") && stdout.contains(" frames at 60 Hz"), "{stdout}");
    assert_eq!(stdout.lines().last(), Some("ok"), "{stdout}");
}
