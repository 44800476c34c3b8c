use std::{env, fs, path::PathBuf, process::Command};
fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").unwrap());
    fs::copy("memory.x", out.join("memory.x")).unwrap();
    // cortex-m-rt's `device` feature includes a `device.x` (a PAC's handler names); this board
    // names its one interrupt handler in `board.rs` itself, so the file is empty.
    fs::write(out.join("device.x"), "").unwrap();
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    if env::var("TARGET").as_deref() == Ok("thumbv7em-none-eabihf") {
        link_newlib_nano();
    }
}

/// The toolchain's size-optimised C library, newlib-nano (Debian's libnewlib-arm-none-eabi),
/// provides memcpy and memset: about 0.5 KB instead of compiler-builtins' 2 KB, which are
/// written for speed. Its archive comes before compiler-builtins on the link line, so
/// compiler-builtins' weak definitions of the same names stay out. The multilib is the one
/// arm-none-eabi-gcc picks for this core and its FPU.
fn link_newlib_nano() {
    let out = Command::new("arm-none-eabi-gcc")
        .args([
            "-mcpu=cortex-m4",
            "-mthumb",
            "-mfloat-abi=hard",
            "-mfpu=fpv4-sp-d16",
        ])
        .arg("-print-file-name=libc_nano.a")
        .output()
        .expect("arm-none-eabi-gcc is needed (scripts/deps.sh installs it)");
    let lib = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim());
    assert!(
        lib.is_absolute() && lib.exists(),
        "newlib-nano's libc_nano.a was not found (scripts/deps.sh installs libnewlib-arm-none-eabi)"
    );
    println!(
        "cargo:rustc-link-search={}",
        lib.parent().unwrap().display()
    );
    println!("cargo:rustc-link-lib=static=c_nano");
}
