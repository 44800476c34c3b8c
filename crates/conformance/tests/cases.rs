//! One test per catalogue case, each run for every model (th, e-series, tmi) on the virtual
//! clock. A case not applicable to a model prints the catalogue's reason.

macro_rules! case_tests {
    ($( $name:ident $id:literal ;)*) => {
        $( #[test] fn $name() { canpos_conformance::run_all_models($id); } )*
        /// The list below covers the catalogue exactly (no case forgotten, none invented).
        #[test]
        fn every_case_has_a_test() {
            let ids = [$($id),*];
            let all: Vec<&str> = canpos_conformance::CASES.iter().map(|c| c.id).collect();
            assert_eq!(ids.to_vec(), all);
        }
    };
}

case_tests! {
    eds_01_static_check "EDS-01";
    sdo_01_expedited_read_device_type "SDO-01";
    sdo_02_read_write_back "SDO-02";
    sdo_03_write_read_only "SDO-03";
    sdo_04_read_write_only "SDO-04";
    sdo_05_no_sub_index "SDO-05";
    sdo_06_no_object "SDO-06";
    sdo_07_invalid_command_specifier "SDO-07";
    sdo_08_too_many_bytes "SDO-08";
    sdo_09_too_few_bytes "SDO-09";
    sdo_10_value_above_maximum "SDO-10";
    sdo_11_value_below_minimum "SDO-11";
    sdo_12_sdo_cob_ids "SDO-12";
    sdo_13_upload_4_bytes "SDO-13";
    sdo_14_segmented_write_guard_time "SDO-14";
    sdo_15_segmented_write_heartbeat "SDO-15";
    sdo_16_segmented_read "SDO-16";
    sdo_17_wrong_toggle "SDO-17";
    sdo_18_segmented_read_again "SDO-18";
    sdo_19_block_upload "SDO-19";
    sdo_20_block_write_guard_time "SDO-20";
    sdo_21_block_download "SDO-21";
    sdo_22_block_upload_1008 "SDO-22";
    sdo_23_block_upload_crc "SDO-23";
    sdo_24_block_write_guard_time_crc "SDO-24";
    sdo_25_block_download_crc "SDO-25";
    sdo_26_illegal_block_size "SDO-26";
    sdo_27_illegal_ack_sequence "SDO-27";
    sdo_28_extra_sdo_servers "SDO-28";
    sdo_29_extra_servers_reset_comm "SDO-29";
    sdo_30_sdo_client_objects "SDO-30";
    pdo_01_rpdo_scan "PDO-01";
    pdo_02_tpdo_scan "PDO-02";
    pdo_03_rtr_operational "PDO-03";
    pdo_04_event_driven_operational "PDO-04";
    pdo_05_event_timer_operational "PDO-05";
    pdo_06_sync_cyclic_type_1 "PDO-06";
    pdo_07_sync_acyclic_type_0 "PDO-07";
    pdo_08_sync_start_value "PDO-08";
    pdo_09_rtr_stopped "PDO-09";
    pdo_10_event_driven_stopped "PDO-10";
    pdo_11_event_timer_stopped "PDO-11";
    pdo_12_type_1_stopped "PDO-12";
    pdo_13_type_0_stopped "PDO-13";
    pdo_14_start_value_stopped "PDO-14";
    pdo_15_rtr_pre_operational "PDO-15";
    pdo_16_event_driven_pre_operational "PDO-16";
    pdo_17_event_timer_pre_operational "PDO-17";
    pdo_18_type_1_pre_operational "PDO-18";
    pdo_19_type_0_pre_operational "PDO-19";
    pdo_20_start_value_pre_operational "PDO-20";
    pdo_21_default_mapping_vs_eds "PDO-21";
    pdo_22_remapping_by_procedure "PDO-22";
    pdo_23_mapping_without_procedure "PDO-23";
    pdo_24_mapping_on_valid_pdo "PDO-24";
    pdo_25_too_many_entries "PDO-25";
    pdo_26_entries_too_long "PDO-26";
    pdo_27_output_into_rpdo "PDO-27";
    pdo_28_input_into_rpdo "PDO-28";
    pdo_29_non_mappable_into_rpdo "PDO-29";
    pdo_30_input_into_tpdo "PDO-30";
    pdo_31_output_into_tpdo "PDO-31";
    pdo_32_non_mappable_into_tpdo "PDO-32";
    pdo_33_dummy_mapping "PDO-33";
    od_01_access_whole_od "OD-01";
    od_02_values_vs_eds_defaults "OD-02";
    od_03_writes_to_ro "OD-03";
    od_04_reads_of_wo "OD-04";
    od_05_sub_index_ff "OD-05";
    od_06_limit_check "OD-06";
    od_07_access_2000_9fff "OD-07";
    od_08_defaults_2000_9fff "OD-08";
    od_09_write_back_2000_9fff "OD-09";
    emcy_01_cob_id "EMCY-01";
    emcy_02_error_register "EMCY-02";
    emcy_03_empty_history "EMCY-03";
    emcy_04_forced_emcy "EMCY-04";
    emcy_05_error_register_after_emcy "EMCY-05";
    emcy_06_history_matches_emcy "EMCY-06";
    sync_01_default_cob_id "SYNC-01";
    sync_02_producer "SYNC-02";
    sync_03_tpdo_every_10th_sync "SYNC-03";
    sync_04_consumer_setup "SYNC-04";
    sync_05_counter_overflow "SYNC-05";
    sync_06_producer_without_counter "SYNC-06";
    sync_07_producer_with_counter "SYNC-07";
    sync_08_producer_save_reset "SYNC-08";
    sync_09_counter_locked "SYNC-09";
    sync_10_store_sync_settings "SYNC-10";
    grd_01_guard_objects "GRD-01";
    grd_02_guarding_reply "GRD-02";
    grd_03_toggle_bit "GRD-03";
    grd_04_id_range "GRD-04";
    grd_05_write_guard_parameters "GRD-05";
    grd_06_life_guarding "GRD-06";
    hb_01_heartbeat_writable "HB-01";
    hb_02_heartbeat_period "HB-02";
    hb_03_heartbeat_off "HB-03";
    hb_04_duplicate_consumer "HB-04";
    hb_05_consumer_producer_faster "HB-05";
    hb_06_consumer_producer_slower "HB-06";
    hb_07_consumer_timeout "HB-07";
    hbg_01_objects_present "HBG-01";
    hbg_02_heartbeat_off "HBG-02";
    hbg_03_guarding_heartbeat_off "HBG-03";
    hbg_04_guarding_off_heartbeat_on "HBG-04";
    hbg_05_heartbeat_plus_rtrs "HBG-05";
    hbg_06_both_configured "HBG-06";
    hbg_07_both_plus_rtrs "HBG-07";
    oth_01_wrong_signature_1010_01 "OTH-01";
    oth_02_save_all "OTH-02";
    oth_03_wrong_signature_1011_01 "OTH-03";
    oth_04_restore_all "OTH-04";
    oth_05_wrong_signature_1010_02 "OTH-05";
    oth_06_save_comm "OTH-06";
    oth_07_wrong_signature_1011_02 "OTH-07";
    oth_08_restore_comm "OTH-08";
    oth_09_verify_configuration "OTH-09";
    oth_10_restricted_cob_ids "OTH-10";
    state_01_boot_up_and_defaults "STATE-01";
    state_02_pre_operational "STATE-02";
    state_03_operational "STATE-03";
    state_04_stopped "STATE-04";
    trans_01_reset_node_reset_comm "TRANS-01";
    trans_02_enter_pre_operational "TRANS-02";
    trans_03_start_remote_node "TRANS-03";
    trans_04_stop_remote_node "TRANS-04";
}
