//! Instance, device choice, required features, queue, allocator, validation messages,
//! one-shot submissions with bounded fence waits.

use std::ffi::{c_void, CStr, CString};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use ash::{ext, khr, vk};
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};

use super::vk_err;
use crate::error::{Error, Result};

const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

/// The wait for one submission unless `VKDR_FENCE_TIMEOUT_S` says otherwise.
const DEFAULT_FENCE_TIMEOUT: Duration = Duration::from_secs(300);

/// `VKDR_FENCE_TIMEOUT_S`: `None` when unset, an error unless it is a positive number of
/// seconds a `Duration` holds.
fn fence_timeout_from_env() -> Result<Option<Duration>> {
    let Ok(text) = std::env::var("VKDR_FENCE_TIMEOUT_S") else {
        return Ok(None);
    };
    text.trim()
        .parse::<f64>()
        .ok()
        .filter(|s| *s > 0.0)
        .and_then(|s| Duration::try_from_secs_f64(s).ok())
        .map(Some)
        .ok_or_else(|| {
            Error::InvalidInput(format!(
                "VKDR_FENCE_TIMEOUT_S='{text}' is not a positive number of seconds"
            ))
        })
}

/// How to create a [`Context`].
#[derive(Clone, Debug)]
pub struct ContextOptions {
    /// Turn on the Khronos validation layer; errors it reports are collected and can
    /// be checked with [`Context::check_validation`]. Also on with `VKDR_VALIDATION=1`.
    pub validation: bool,
    /// Pick a device by index (as listed by `vkdr info`) or by a case-insensitive
    /// substring of its name. Defaults to `VKDR_DEVICE`, else the best device:
    /// discrete GPU, then integrated, then virtual, then CPU.
    pub device: Option<String>,
    /// Longest wait for one submission before giving up with [`Error::Timeout`].
    pub fence_timeout: Duration,
}

impl Default for ContextOptions {
    fn default() -> Self {
        let validation = std::env::var("VKDR_VALIDATION").is_ok_and(|v| v == "1");
        // An invalid value is refused by `Context::new`; here it leaves the default.
        let fence_timeout = fence_timeout_from_env()
            .ok()
            .flatten()
            .unwrap_or(DEFAULT_FENCE_TIMEOUT);
        Self {
            validation,
            device: std::env::var("VKDR_DEVICE").ok(),
            fence_timeout,
        }
    }
}

/// What `vkdr info` prints about the chosen device.
#[derive(Clone, Debug)]
pub struct DeviceInfo {
    /// Position in the loader's device list (what `VKDR_DEVICE` takes as a number).
    pub index: usize,
    /// Device name as the driver reports it.
    pub name: String,
    /// Device type: discrete GPU, integrated GPU, virtual GPU, CPU or other.
    pub kind: String,
    /// Vulkan version the device supports, as major.minor.patch.
    pub api_version: String,
    /// Driver name (empty when the driver does not report one).
    pub driver_name: String,
    /// Driver version and build details (empty when not reported).
    pub driver_info: String,
    /// Bits of sub-pixel precision in rasterization (`subPixelPrecisionBits`).
    pub sub_pixel_precision_bits: u32,
    /// Largest width or height of a 2D image, pixels (`maxImageDimension2D`).
    pub max_image_dimension_2d: u32,
    /// Largest range of one storage-buffer binding, bytes (`maxStorageBufferRange`).
    pub max_storage_buffer_range: u32,
    /// Alignment of a storage-buffer binding's offset, bytes
    /// (`minStorageBufferOffsetAlignment`).
    pub min_storage_buffer_offset_alignment: u64,
    /// Most invocations in one compute workgroup (`maxComputeWorkGroupInvocations`).
    pub max_compute_workgroup_invocations: u32,
    /// Most workgroups one dispatch may have in x, y and z (`maxComputeWorkGroupCount`).
    pub max_compute_workgroup_count: [u32; 3],
    /// Most bytes of push constants a pipeline may have (`maxPushConstantsSize`).
    pub max_push_constants_size: u32,
    /// Descriptors one push-descriptor set can hold (every pipeline's bindings are pushed).
    pub max_push_descriptors: u32,
    /// Most storage buffers one shader stage may bind
    /// (`maxPerStageDescriptorStorageBuffers`).
    pub max_per_stage_storage_buffers: u32,
    /// Invocations per subgroup (the default subgroup size).
    pub subgroup_size: u32,
    /// Workgroups of 64 invocations that a grid-stride pass (one that loops over its
    /// items with the grid's size as stride) is dispatched with at most: enough to fill a
    /// GPU, and a few per core on a CPU driver, where every invocation pays again for what
    /// it loads before its loop (at 1e5 vertices the pose pass took 9 ms on lavapipe
    /// with 4096 workgroups, about 1 ms with 32).
    pub grid_groups: u32,
    /// Nanoseconds per timestamp tick (`timestampPeriod`).
    pub timestamp_period_ns: f32,
    /// Each feature the engine needs, by name, and whether the device has it, in the
    /// order `vkdr info` prints.
    pub features: Vec<(&'static str, bool)>,
}

/// A handle to one Vulkan device and everything needed to use it. Cheap to clone.
#[derive(Clone)]
pub struct Context {
    pub(crate) shared: Arc<Shared>,
}

pub(crate) struct Shared {
    pub(crate) entry: ash::Entry,
    pub(crate) instance: ash::Instance,
    pub(crate) device: ash::Device,
    pub(crate) queue: vk::Queue,
    pub(crate) command_pool: Mutex<vk::CommandPool>,
    pub(crate) allocator: Mutex<Option<Allocator>>,
    pub(crate) push_descriptor: khr::push_descriptor::Device,
    pub(crate) debug_device: Option<ext::debug_utils::Device>,
    debug: Option<(ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    validation_messages: Box<Mutex<Vec<String>>>,
    pub(crate) info: DeviceInfo,
    pub(crate) fence_timeout: Duration,
}

/// Feature names and whether the device has them, in the order `vkdr info` prints.
struct FeatureSupport {
    features: Vec<(&'static str, bool)>,
}

impl Context {
    /// Creates a context with options from the environment (`VKDR_VALIDATION`,
    /// `VKDR_DEVICE`, `VKDR_FENCE_TIMEOUT_S`; an invalid timeout is an error).
    pub fn new() -> Result<Self> {
        fence_timeout_from_env()?;
        Self::with_options(ContextOptions::default())
    }

    /// Creates a context with explicit options. Fails with [`Error::Loader`] without a Vulkan
    /// loader, [`Error::NoDevice`] when no device matches, and [`Error::MissingFeatures`] when
    /// the matching devices lack a feature the engine needs.
    pub fn with_options(options: ContextOptions) -> Result<Self> {
        let _serial = lifecycle();
        // SAFETY: loading the Vulkan loader library; its entry points are trusted.
        let entry = unsafe { ash::Entry::load() }.map_err(|e| {
            Error::Loader(format!(
                "cannot load the Vulkan loader ({e}); install it with tools/setup.sh \
                 (Debian: libvulkan1 mesa-vulkan-drivers)"
            ))
        })?;
        let instance = create_instance(&entry, options.validation)?;
        let validation_messages: Box<Mutex<Vec<String>>> = Box::default();
        let debug = if options.validation {
            // SAFETY: the messenger's user data points into a Box that Shared owns and
            // drops only after destroying the messenger.
            Some(unsafe { create_messenger(&entry, &instance, &validation_messages) }?)
        } else {
            None
        };

        let chosen = choose_device(&instance, options.device.as_deref());
        let (physical_device, info) = match chosen {
            Ok(found) => found,
            Err(e) => {
                // SAFETY: nothing was created from the instance but the messenger.
                unsafe {
                    if let Some((loader, messenger)) = &debug {
                        loader.destroy_debug_utils_messenger(*messenger, None);
                    }
                    instance.destroy_instance(None);
                }
                return Err(e);
            }
        };

        // SAFETY: valid instance and physical device.
        let queue_family =
            unsafe { instance.get_physical_device_queue_family_properties(physical_device) }
                .iter()
                .position(|q| {
                    q.queue_flags
                        .contains(vk::QueueFlags::GRAPHICS | vk::QueueFlags::COMPUTE)
                        && q.timestamp_valid_bits > 0
                })
                .ok_or_else(|| {
                    Error::NoDevice(format!(
                        "'{}' has no queue with graphics, compute and timestamps",
                        info.name
                    ))
                })? as u32;

        let device = create_device(&instance, physical_device, queue_family)?;
        // SAFETY: queue family and index 0 exist (created above).
        let queue = unsafe { device.get_device_queue(queue_family, 0) };
        let pool_info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(queue_family)
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        // SAFETY: valid device.
        let command_pool = unsafe { device.create_command_pool(&pool_info, None) }
            .map_err(vk_err("vkCreateCommandPool"))?;
        let allocator = Allocator::new(&AllocatorCreateDesc {
            instance: instance.clone(),
            device: device.clone(),
            physical_device,
            debug_settings: Default::default(),
            buffer_device_address: false,
            allocation_sizes: Default::default(),
        })
        .map_err(|e| Error::Allocation {
            name: "allocator".into(),
            reason: e.to_string(),
        })?;
        let push_descriptor = khr::push_descriptor::Device::new(&instance, &device);
        let debug_device = debug
            .as_ref()
            .map(|_| ext::debug_utils::Device::new(&instance, &device));

        Ok(Self {
            shared: Arc::new(Shared {
                entry,
                instance,
                device,
                queue,
                command_pool: Mutex::new(command_pool),
                allocator: Mutex::new(Some(allocator)),
                push_descriptor,
                debug_device,
                debug,
                validation_messages,
                info,
                fence_timeout: options.fence_timeout,
            }),
        })
    }

    /// The chosen device, its driver, limits and features.
    pub fn info(&self) -> &DeviceInfo {
        &self.shared.info
    }

    /// Every Vulkan device the loader reports, with its index for `VKDR_DEVICE`.
    pub fn list_devices() -> Result<Vec<String>> {
        let _serial = lifecycle();
        // SAFETY: as in `with_options`.
        let entry = unsafe { ash::Entry::load() }
            .map_err(|e| Error::Loader(format!("cannot load the Vulkan loader ({e})")))?;
        let instance = create_instance(&entry, false)?;
        // SAFETY: valid instance, destroyed before returning.
        let names = unsafe {
            let devices = instance.enumerate_physical_devices();
            let names = devices.map(|devices| {
                devices
                    .iter()
                    .map(|&pd| device_name(&instance.get_physical_device_properties(pd)))
                    .collect()
            });
            instance.destroy_instance(None);
            names
        };
        names.map_err(vk_err("vkEnumeratePhysicalDevices"))
    }

    /// Validation errors reported since the last call (empty without validation).
    pub fn take_validation_errors(&self) -> Vec<String> {
        std::mem::take(&mut *self.shared.validation_messages.lock().unwrap())
    }

    /// Fails with [`Error::Validation`] if the validation layer reported any error.
    pub fn check_validation(&self) -> Result<()> {
        let errors = self.take_validation_errors();
        if errors.is_empty() {
            Ok(())
        } else {
            Err(Error::Validation(errors))
        }
    }

    pub(crate) fn device(&self) -> &ash::Device {
        &self.shared.device
    }

    /// Names a Vulkan object for validation messages (only with validation on).
    pub(crate) fn name_object<H: vk::Handle>(&self, handle: H, name: &str) {
        if let Some(debug) = &self.shared.debug_device {
            let name = CString::new(name.replace('\0', " ")).unwrap_or_default();
            let info = vk::DebugUtilsObjectNameInfoEXT::default()
                .object_handle(handle)
                .object_name(&name);
            // SAFETY: the handle belongs to this device; naming is best effort.
            let _ = unsafe { debug.set_debug_utils_object_name(&info) };
        }
    }

    pub(crate) fn with_allocator<T>(&self, f: impl FnOnce(&mut Allocator) -> T) -> T {
        let mut guard = self.shared.allocator.lock().unwrap();
        f(guard
            .as_mut()
            .expect("allocator lives as long as the context"))
    }

    pub(crate) fn allocate_command_buffer(&self) -> Result<vk::CommandBuffer> {
        let pool = self.shared.command_pool.lock().unwrap();
        let info = vk::CommandBufferAllocateInfo::default()
            .command_pool(*pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: the pool is externally synchronised by the mutex.
        let buffers = unsafe { self.device().allocate_command_buffers(&info) }
            .map_err(vk_err("vkAllocateCommandBuffers"))?;
        Ok(buffers[0])
    }

    pub(crate) fn free_command_buffer(&self, command_buffer: vk::CommandBuffer) {
        let pool = self.shared.command_pool.lock().unwrap();
        // SAFETY: callers free a command buffer only once its execution has completed.
        unsafe { self.device().free_command_buffers(*pool, &[command_buffer]) };
    }

    /// Submits one command buffer and waits (bounded) for it to complete.
    pub(crate) fn submit_command_buffer(&self, command_buffer: vk::CommandBuffer) -> Result<()> {
        let device = self.device();
        // SAFETY: fence created and destroyed here; the command buffer is fully recorded,
        // and the queue is used from one thread at a time (submissions block until done).
        unsafe {
            let fence = device
                .create_fence(&vk::FenceCreateInfo::default(), None)
                .map_err(vk_err("vkCreateFence"))?;
            let buffers = [vk::CommandBufferSubmitInfo::default().command_buffer(command_buffer)];
            let submit = vk::SubmitInfo2::default().command_buffer_infos(&buffers);
            let submitted = device
                .queue_submit2(self.shared.queue, &[submit], fence)
                .map_err(vk_err("vkQueueSubmit2"));
            let waited = submitted.and_then(|()| {
                let timeout = self.shared.fence_timeout;
                match device.wait_for_fences(&[fence], true, timeout.as_nanos() as u64) {
                    Ok(()) => Ok(()),
                    Err(vk::Result::TIMEOUT) => Err(Error::Timeout {
                        what: "a GPU submission",
                        seconds: timeout.as_secs_f64(),
                    }),
                    Err(e) => Err(vk_err("vkWaitForFences")(e)),
                }
            });
            if waited.is_ok() {
                device.destroy_fence(fence, None);
            }
            // On timeout the fence is leaked on purpose: the device may still signal it.
            waited?;
        }
        // A submission that the validation layer objected to has no trustworthy result.
        self.check_validation()
    }
}

impl Drop for Shared {
    fn drop(&mut self) {
        let _serial = lifecycle();
        // SAFETY: the last handle is gone, so no resource remains; wait for the device,
        // then destroy in reverse order of creation.
        unsafe {
            let _ = self.device.device_wait_idle();
            self.allocator.lock().unwrap().take();
            self.device
                .destroy_command_pool(*self.command_pool.get_mut().unwrap(), None);
            self.device.destroy_device(None);
            if let Some((loader, messenger)) = &self.debug {
                loader.destroy_debug_utils_messenger(*messenger, None);
            }
            self.instance.destroy_instance(None);
        }
        let _ = &self.entry;
    }
}

/// Held while a context is created or destroyed: instances and devices made and destroyed
/// on several threads at once (the tests run in parallel, each with its own context) are
/// a known source of driver crashes, and one test binary (`tests/cpd.rs`) once ended in a
/// segmentation fault on lavapipe under load. Contexts are few, so nothing waits long.
fn lifecycle() -> std::sync::MutexGuard<'static, ()> {
    static LIFECYCLE: Mutex<()> = Mutex::new(());
    LIFECYCLE
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

fn create_instance(entry: &ash::Entry, validation: bool) -> Result<ash::Instance> {
    let app = vk::ApplicationInfo::default()
        .application_name(c"vkdr")
        .engine_name(c"vkdr")
        .api_version(vk::API_VERSION_1_3);
    let mut layers = Vec::new();
    let mut extensions = Vec::new();
    if validation {
        // SAFETY: plain enumeration.
        let available = unsafe { entry.enumerate_instance_layer_properties() }
            .map_err(vk_err("vkEnumerateInstanceLayerProperties"))?;
        let found = available
            .iter()
            .any(|l| l.layer_name_as_c_str().is_ok_and(|n| n == VALIDATION_LAYER));
        if !found {
            return Err(Error::Loader(
                "validation was asked for but VK_LAYER_KHRONOS_validation is not installed \
                 (Debian: vulkan-validationlayers; tools/setup.sh installs it)"
                    .into(),
            ));
        }
        layers.push(VALIDATION_LAYER.as_ptr());
        extensions.push(ext::debug_utils::NAME.as_ptr());
    }
    let info = vk::InstanceCreateInfo::default()
        .application_info(&app)
        .enabled_layer_names(&layers)
        .enabled_extension_names(&extensions);
    // SAFETY: all pointers in `info` outlive the call.
    unsafe { entry.create_instance(&info, None) }.map_err(|e| match e {
        vk::Result::ERROR_INCOMPATIBLE_DRIVER => Error::Loader(
            "no Vulkan 1.3 driver found; install one (tools/setup.sh installs Mesa's lavapipe)"
                .into(),
        ),
        e => vk_err("vkCreateInstance")(e),
    })
}

unsafe extern "system" fn on_validation_message(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _kind: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user: *mut c_void,
) -> vk::Bool32 {
    // SAFETY: the layer passes valid callback data; `user` is the Box<Mutex<Vec<String>>>
    // installed in `create_messenger`, alive until the messenger is destroyed.
    unsafe {
        let message = data
            .as_ref()
            .and_then(|d| d.message_as_c_str())
            .map(|m| m.to_string_lossy().into_owned())
            .unwrap_or_default();
        if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::ERROR) {
            eprintln!("[vulkan validation error] {message}");
            let messages = &*(user as *const Mutex<Vec<String>>);
            if let Ok(mut messages) = messages.lock() {
                messages.push(message);
            }
        } else {
            eprintln!("[vulkan validation warning] {message}");
        }
    }
    vk::FALSE
}

/// # Safety
/// `messages` must outlive the returned messenger.
unsafe fn create_messenger(
    entry: &ash::Entry,
    instance: &ash::Instance,
    messages: &Mutex<Vec<String>>,
) -> Result<(ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)> {
    let loader = ext::debug_utils::Instance::new(entry, instance);
    let info = vk::DebugUtilsMessengerCreateInfoEXT::default()
        .message_severity(
            vk::DebugUtilsMessageSeverityFlagsEXT::ERROR
                | vk::DebugUtilsMessageSeverityFlagsEXT::WARNING,
        )
        .message_type(
            vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                | vk::DebugUtilsMessageTypeFlagsEXT::GENERAL,
        )
        .pfn_user_callback(Some(on_validation_message))
        .user_data(messages as *const Mutex<Vec<String>> as *mut c_void);
    // SAFETY: forwarded to the caller.
    let messenger = unsafe { loader.create_debug_utils_messenger(&info, None) }
        .map_err(vk_err("vkCreateDebugUtilsMessengerEXT"))?;
    Ok((loader, messenger))
}

fn device_name(props: &vk::PhysicalDeviceProperties) -> String {
    props
        .device_name_as_c_str()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|_| "unnamed device".into())
}

fn type_rank(kind: vk::PhysicalDeviceType) -> u32 {
    match kind {
        vk::PhysicalDeviceType::DISCRETE_GPU => 0,
        vk::PhysicalDeviceType::INTEGRATED_GPU => 1,
        vk::PhysicalDeviceType::VIRTUAL_GPU => 2,
        vk::PhysicalDeviceType::CPU => 3,
        _ => 4,
    }
}

fn grid_groups(kind: vk::PhysicalDeviceType) -> u32 {
    if kind == vk::PhysicalDeviceType::CPU {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        (16 * cores).clamp(16, 1024) as u32
    } else {
        4096
    }
}

fn type_name(kind: vk::PhysicalDeviceType) -> &'static str {
    match kind {
        vk::PhysicalDeviceType::DISCRETE_GPU => "discrete GPU",
        vk::PhysicalDeviceType::INTEGRATED_GPU => "integrated GPU",
        vk::PhysicalDeviceType::VIRTUAL_GPU => "virtual GPU",
        vk::PhysicalDeviceType::CPU => "CPU",
        _ => "other",
    }
}

/// Reads the features the engine needs from one physical device.
fn query_features(instance: &ash::Instance, pd: vk::PhysicalDevice) -> FeatureSupport {
    // SAFETY: valid handles; the feature structs outlive the query.
    unsafe {
        let props = instance.get_physical_device_properties(pd);
        let extensions = instance
            .enumerate_device_extension_properties(pd)
            .unwrap_or_default();
        let has_extension = |name: &CStr| {
            extensions
                .iter()
                .any(|e| e.extension_name_as_c_str().is_ok_and(|n| n == name))
        };
        let api_1_3 = props.api_version >= vk::API_VERSION_1_3;
        let mut atomic_float = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default();
        let mut v12 = vk::PhysicalDeviceVulkan12Features::default();
        let mut v13 = vk::PhysicalDeviceVulkan13Features::default();
        let has_atomic_float_ext = has_extension(ext::shader_atomic_float::NAME);
        if api_1_3 {
            let mut features = vk::PhysicalDeviceFeatures2::default()
                .push_next(&mut v12)
                .push_next(&mut v13);
            if has_atomic_float_ext {
                features = features.push_next(&mut atomic_float);
            }
            instance.get_physical_device_features2(pd, &mut features);
        }
        let core = instance.get_physical_device_features(pd);
        let mut subgroup = vk::PhysicalDeviceSubgroupProperties::default();
        let mut props2 = vk::PhysicalDeviceProperties2::default().push_next(&mut subgroup);
        instance.get_physical_device_properties2(pd, &mut props2);
        let needed_ops = vk::SubgroupFeatureFlags::BASIC
            | vk::SubgroupFeatureFlags::ARITHMETIC
            | vk::SubgroupFeatureFlags::BALLOT
            | vk::SubgroupFeatureFlags::VOTE
            | vk::SubgroupFeatureFlags::SHUFFLE;
        let subgroups_ok = subgroup.supported_operations.contains(needed_ops)
            && subgroup
                .supported_stages
                .contains(vk::ShaderStageFlags::COMPUTE);
        FeatureSupport {
            features: vec![
                ("Vulkan 1.3", api_1_3),
                (
                    "float32 atomic add (VK_EXT_shader_atomic_float)",
                    atomic_float.shader_buffer_float32_atomic_add == vk::TRUE,
                ),
                (
                    "int64 and int64 buffer atomics (deterministic fixed-point sums)",
                    core.shader_int64 == vk::TRUE && v12.shader_buffer_int64_atomics == vk::TRUE,
                ),
                ("timeline semaphores", v12.timeline_semaphore == vk::TRUE),
                ("synchronization2", v13.synchronization2 == vk::TRUE),
                ("dynamic rendering", v13.dynamic_rendering == vk::TRUE),
                (
                    "push descriptors (VK_KHR_push_descriptor)",
                    has_extension(khr::push_descriptor::NAME),
                ),
                (
                    "vertex stage storage buffers",
                    core.vertex_pipeline_stores_and_atomics == vk::TRUE,
                ),
                (
                    "fragment stage storage and atomics",
                    core.fragment_stores_and_atomics == vk::TRUE,
                ),
                (
                    "compute subgroups (basic, arithmetic, ballot, vote, shuffle)",
                    subgroups_ok,
                ),
            ],
        }
    }
}

fn describe(instance: &ash::Instance, pd: vk::PhysicalDevice, index: usize) -> DeviceInfo {
    // SAFETY: valid handles.
    unsafe {
        let mut driver = vk::PhysicalDeviceDriverProperties::default();
        let mut subgroup = vk::PhysicalDeviceSubgroupProperties::default();
        let mut push = vk::PhysicalDevicePushDescriptorPropertiesKHR::default();
        let mut props2 = vk::PhysicalDeviceProperties2::default()
            .push_next(&mut driver)
            .push_next(&mut subgroup)
            .push_next(&mut push);
        instance.get_physical_device_properties2(pd, &mut props2);
        let props = props2.properties;
        let limits = props.limits;
        let v = props.api_version;
        DeviceInfo {
            index,
            name: device_name(&props),
            kind: type_name(props.device_type).into(),
            api_version: format!(
                "{}.{}.{}",
                vk::api_version_major(v),
                vk::api_version_minor(v),
                vk::api_version_patch(v)
            ),
            driver_name: driver
                .driver_name_as_c_str()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
            driver_info: driver
                .driver_info_as_c_str()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
            sub_pixel_precision_bits: limits.sub_pixel_precision_bits,
            max_image_dimension_2d: limits.max_image_dimension2_d,
            max_storage_buffer_range: limits.max_storage_buffer_range,
            min_storage_buffer_offset_alignment: limits.min_storage_buffer_offset_alignment,
            max_compute_workgroup_invocations: limits.max_compute_work_group_invocations,
            max_compute_workgroup_count: limits.max_compute_work_group_count,
            max_push_constants_size: limits.max_push_constants_size,
            max_push_descriptors: push.max_push_descriptors,
            max_per_stage_storage_buffers: limits.max_per_stage_descriptor_storage_buffers,
            subgroup_size: subgroup.subgroup_size,
            grid_groups: grid_groups(props.device_type),
            timestamp_period_ns: limits.timestamp_period,
            features: query_features(instance, pd).features,
        }
    }
}

fn choose_device(
    instance: &ash::Instance,
    wanted: Option<&str>,
) -> Result<(vk::PhysicalDevice, DeviceInfo)> {
    // SAFETY: valid instance.
    let devices = unsafe { instance.enumerate_physical_devices() }
        .map_err(vk_err("vkEnumeratePhysicalDevices"))?;
    if devices.is_empty() {
        return Err(Error::NoDevice(
            "the Vulkan loader reports no device; install a driver (tools/setup.sh installs \
             Mesa's lavapipe)"
                .into(),
        ));
    }
    let described: Vec<(vk::PhysicalDevice, DeviceInfo, u32)> = devices
        .iter()
        .enumerate()
        .map(|(i, &pd)| {
            // SAFETY: valid handles.
            let kind = unsafe { instance.get_physical_device_properties(pd) }.device_type;
            (pd, describe(instance, pd, i), type_rank(kind))
        })
        .collect();
    let all_names = described
        .iter()
        .map(|(_, d, _)| format!("{}: {}", d.index, d.name))
        .collect::<Vec<_>>()
        .join(", ");

    let candidates: Vec<&(vk::PhysicalDevice, DeviceInfo, u32)> = match wanted {
        Some(w) if !w.trim().is_empty() => {
            let w = w.trim();
            let picked: Vec<_> = match w.parse::<usize>() {
                Ok(i) => described.iter().filter(|(_, d, _)| d.index == i).collect(),
                Err(_) => described
                    .iter()
                    .filter(|(_, d, _)| d.name.to_lowercase().contains(&w.to_lowercase()))
                    .collect(),
            };
            if picked.is_empty() {
                return Err(Error::NoDevice(format!(
                    "VKDR_DEVICE='{w}' matches none of: {all_names}"
                )));
            }
            picked
        }
        _ => {
            let mut sorted: Vec<_> = described.iter().collect();
            sorted.sort_by_key(|(_, d, rank)| (*rank, d.index));
            sorted
        }
    };
    let mut first_missing = None;
    for (pd, info, _) in &candidates {
        let missing: Vec<String> = info
            .features
            .iter()
            .filter(|(_, has)| !has)
            .map(|(n, _)| n.to_string())
            .collect();
        if missing.is_empty() {
            return Ok((*pd, info.clone()));
        }
        first_missing.get_or_insert(Error::MissingFeatures {
            device: info.name.clone(),
            missing,
        });
    }
    Err(first_missing.expect("candidates is not empty"))
}

fn create_device(
    instance: &ash::Instance,
    pd: vk::PhysicalDevice,
    queue_family: u32,
) -> Result<ash::Device> {
    let priorities = [1.0];
    let queues = [vk::DeviceQueueCreateInfo::default()
        .queue_family_index(queue_family)
        .queue_priorities(&priorities)];
    let extensions = [
        ext::shader_atomic_float::NAME.as_ptr(),
        khr::push_descriptor::NAME.as_ptr(),
    ];
    let core = vk::PhysicalDeviceFeatures::default()
        .vertex_pipeline_stores_and_atomics(true)
        .fragment_stores_and_atomics(true)
        .shader_int64(true);
    let mut v12 = vk::PhysicalDeviceVulkan12Features::default()
        .timeline_semaphore(true)
        .shader_buffer_int64_atomics(true);
    let mut v13 = vk::PhysicalDeviceVulkan13Features::default()
        .synchronization2(true)
        .dynamic_rendering(true);
    let mut atomic_float = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default()
        .shader_buffer_float32_atomic_add(true);
    let mut features = vk::PhysicalDeviceFeatures2::default()
        .features(core)
        .push_next(&mut v12)
        .push_next(&mut v13)
        .push_next(&mut atomic_float);
    let info = vk::DeviceCreateInfo::default()
        .queue_create_infos(&queues)
        .enabled_extension_names(&extensions)
        .push_next(&mut features);
    // SAFETY: features were checked in `choose_device`; pointers outlive the call.
    unsafe { instance.create_device(pd, &info, None) }.map_err(vk_err("vkCreateDevice"))
}
