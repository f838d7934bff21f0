//! Turns the opt-in test variables into cfgs, so a test that cannot check
//! anything without them is compiled as ignored (shown as such, with the
//! reason) instead of passing without checking.

fn main() {
    for (variable, cfg) in [
        ("SHADOWCULL_REALDATA", "shadowcull_realdata"),
        ("SHADOWCULL_SLOW", "shadowcull_slow"),
        ("SHADOWCULL_BROWSER", "shadowcull_browser"),
    ] {
        println!("cargo::rustc-check-cfg=cfg({cfg})");
        println!("cargo::rerun-if-env-changed={variable}");
        if std::env::var_os(variable).is_some_and(|v| !v.is_empty()) {
            println!("cargo::rustc-cfg={cfg}");
        }
    }
    println!("cargo::rerun-if-changed=build.rs");
}
