//! Compiles every shader in `glsl/` to SPIR-V with shaderc. `glsl/include/` holds the
//! shared GLSL that shaders `#include`; each stage file becomes `$OUT_DIR/<name>.spv`.

use std::path::{Path, PathBuf};
use std::{env, fs};

fn main() {
    let glsl = Path::new("glsl");
    let out = PathBuf::from(env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    println!("cargo:rerun-if-changed=glsl");

    let compiler = shaderc::Compiler::new().expect("shaderc compiler");
    let mut stages: Vec<PathBuf> = fs::read_dir(glsl)
        .expect("glsl/ directory")
        .map(|entry| entry.expect("glsl/ entry").path())
        .filter(|path| stage_of(path).is_some())
        .collect();
    stages.sort();

    for path in stages {
        println!("cargo:rerun-if-changed={}", path.display());
        let source = fs::read_to_string(&path).expect("shader source");
        let mut options = shaderc::CompileOptions::new().expect("shaderc options");
        options.set_target_env(
            shaderc::TargetEnv::Vulkan,
            shaderc::EnvVersion::Vulkan1_2 as u32,
        );
        options.set_optimization_level(shaderc::OptimizationLevel::Performance);
        options.set_generate_debug_info();
        options.set_include_callback(|name, _kind, _from, _depth| {
            let include = glsl.join("include").join(name);
            fs::read_to_string(&include)
                .map(|content| shaderc::ResolvedInclude {
                    resolved_name: include.display().to_string(),
                    content,
                })
                .map_err(|e| format!("{}: {e}", include.display()))
        });
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let kind = stage_of(&path).unwrap();
        let artifact = compiler
            .compile_into_spirv(&source, kind, &name, "main", Some(&options))
            .unwrap_or_else(|e| panic!("compiling {}: {e}", path.display()));
        fs::write(out.join(format!("{name}.spv")), artifact.as_binary_u8()).expect("write SPIR-V");
    }
}

fn stage_of(path: &Path) -> Option<shaderc::ShaderKind> {
    match path.extension()?.to_str()? {
        "vert" => Some(shaderc::ShaderKind::Vertex),
        "frag" => Some(shaderc::ShaderKind::Fragment),
        "comp" => Some(shaderc::ShaderKind::Compute),
        _ => None,
    }
}
