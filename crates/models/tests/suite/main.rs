//! The tests of the stack, the encoder and the models, in one binary (they run the three
//! products' nodes): every file is a module named after the rule set it
//! states (CiA 301 / 305 / 406 clause, manual table or property). One binary links once,
//! which keeps `cargo test` and the mutation runs (docs/MUTANTS.md) short.

mod common;

mod app_defaults;
mod can_frame_format;
mod cia301_cob_id_objects;
mod cia301_data_types_and_aborts;
mod cia301_error_behaviour;
mod cia301_error_control;
mod cia301_error_history;
mod cia301_node_guarding_frames;
mod cia301_pdo_mapping_and_triggers;
mod cia301_pdo_rules;
mod cia301_pdo_timers;
mod cia301_predefined_cob_ids;
mod cia301_sdo_command_bytes;
mod cia301_sdo_sizes;
mod cia301_sdo_transfer_types;
mod cia301_store_restore_scopes;
mod cia301_sync_consumer;
mod cia301_tpdo_host_view;
mod cia305_lss_states;
mod cia406_cams_and_work_areas;
mod cia406_parameter_writes;
mod cia406_position_channels;
mod d13_sensor_error_emcy;
mod d15_stored_cob_ids;
mod d19_temperature_record;
mod default_tpdo_mappings;
mod e_series_offset_6509;
mod eds_export;
mod encoder_scenarios;
mod frame_sequence_props;
mod lss_manual_examples;
mod lss_props;
mod lss_waiting;
mod manual_tables;
mod model_od;
mod model_particulars;
mod model_tables;
mod model_variants;
mod node_rules;
mod od_rows;
mod poll_equivalence;
mod process_values;
mod reset_node_application;
mod sdo_aborts;
mod sdo_manual_tables;
mod sdo_props;
mod sdo_transfers;
mod smoke;
mod spec11_fault_conditions;
mod stack_on_models;
mod storage_image_format;
mod storage_roundtrip;
mod tmi_emcy_and_status;
mod tmi_preset_cia406;
mod tmi_r27_event_timer;
mod tmi_storage;
