//! The parameter services every rclcpp and rclpy node offers (`~/list_parameters`,
//! `~/get_parameters`, `~/get_parameter_types`, `~/describe_parameters`, `~/set_parameters`,
//! `~/set_parameters_atomically`, types of `rcl_interfaces`), so that `ros2 param list`,
//! `ros2 param get` and `ros2 param dump` answer for rollbase as for any node instead of
//! waiting for a service that is not there.
//!
//! rollbase has no ROS parameters: its configuration is the platform file and the command
//! line, fixed for a run (a base's limits do not change under a moving platform). So the node
//! lists none, reports every name as not set (type 0, `PARAMETER_NOT_SET`), and refuses every
//! set with a reason that says where the setting lives. The answers are pure functions of the
//! requests ([`answer_list`] …); the node serves them in each caller's mapping like `~/stop`.
//!
//! The types follow the `.msg`/`.srv` files of rcl_interfaces (the same in Humble and Jazzy),
//! fields in order, for CDR.

use super::msg::{MsgDef, RosMsg};
use serde::{Deserialize, Serialize};

macro_rules! srvdef {
    ($ty:ty, $ident:ident, $name:literal) => {
        static $ident: MsgDef = MsgDef {
            name: $name,
            text: "",
            deps: &[],
        };
        impl RosMsg for $ty {
            const DEF: &'static MsgDef = &$ident;
        }
    };
}

/// `rcl_interfaces/msg/ParameterValue`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ParameterValue {
    /// `ParameterType` (0: not set).
    #[serde(rename = "type")]
    pub kind: u8,
    /// bool_value.
    pub bool_value: bool,
    /// integer_value.
    pub integer_value: i64,
    /// double_value.
    pub double_value: f64,
    /// string_value.
    pub string_value: String,
    /// byte_array_value.
    pub byte_array_value: Vec<u8>,
    /// bool_array_value.
    pub bool_array_value: Vec<bool>,
    /// integer_array_value.
    pub integer_array_value: Vec<i64>,
    /// double_array_value.
    pub double_array_value: Vec<f64>,
    /// string_array_value.
    pub string_array_value: Vec<String>,
}

/// `rcl_interfaces/msg/Parameter`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Parameter {
    /// Name.
    pub name: String,
    /// Value.
    pub value: ParameterValue,
}

/// `rcl_interfaces/msg/SetParametersResult`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SetParametersResult {
    /// Whether it was set.
    pub successful: bool,
    /// Why not.
    pub reason: String,
}

/// `rcl_interfaces/msg/FloatingPointRange`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FloatingPointRange {
    /// from_value.
    pub from_value: f64,
    /// to_value.
    pub to_value: f64,
    /// step.
    pub step: f64,
}

/// `rcl_interfaces/msg/IntegerRange`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct IntegerRange {
    /// from_value.
    pub from_value: i64,
    /// to_value.
    pub to_value: i64,
    /// step.
    pub step: u64,
}

/// `rcl_interfaces/msg/ParameterDescriptor`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ParameterDescriptor {
    /// name.
    pub name: String,
    /// type.
    #[serde(rename = "type")]
    pub kind: u8,
    /// description.
    pub description: String,
    /// additional_constraints.
    pub additional_constraints: String,
    /// read_only.
    pub read_only: bool,
    /// dynamic_typing.
    pub dynamic_typing: bool,
    /// floating_point_range (at most 1).
    pub floating_point_range: Vec<FloatingPointRange>,
    /// integer_range (at most 1).
    pub integer_range: Vec<IntegerRange>,
}

/// `rcl_interfaces/srv/ListParameters` request.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ListParametersRequest {
    /// prefixes.
    pub prefixes: Vec<String>,
    /// depth.
    pub depth: u64,
}
/// `rcl_interfaces/srv/ListParameters` response.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ListParametersResponse {
    /// result.names.
    pub names: Vec<String>,
    /// result.prefixes.
    pub prefixes: Vec<String>,
}
/// A request naming parameters (`GetParameters`, `GetParameterTypes`, `DescribeParameters`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NamesRequest {
    /// names.
    pub names: Vec<String>,
}
/// `rcl_interfaces/srv/GetParameters` request.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GetParametersRequest(pub NamesRequest);
/// `rcl_interfaces/srv/GetParameters` response.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GetParametersResponse {
    /// values.
    pub values: Vec<ParameterValue>,
}
/// `rcl_interfaces/srv/GetParameterTypes` request.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GetParameterTypesRequest(pub NamesRequest);
/// `rcl_interfaces/srv/GetParameterTypes` response.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GetParameterTypesResponse {
    /// types.
    pub types: Vec<u8>,
}
/// `rcl_interfaces/srv/DescribeParameters` request.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DescribeParametersRequest(pub NamesRequest);
/// `rcl_interfaces/srv/DescribeParameters` response.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DescribeParametersResponse {
    /// descriptors.
    pub descriptors: Vec<ParameterDescriptor>,
}
/// `rcl_interfaces/srv/SetParameters` request (also `SetParametersAtomically`'s).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SetParametersRequest {
    /// parameters.
    pub parameters: Vec<Parameter>,
}
/// `rcl_interfaces/srv/SetParametersAtomically` request.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SetParametersAtomicallyRequest(pub SetParametersRequest);
/// `rcl_interfaces/srv/SetParameters` response.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SetParametersResponse {
    /// results, one per parameter.
    pub results: Vec<SetParametersResult>,
}
/// `rcl_interfaces/srv/SetParametersAtomically` response.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SetParametersAtomicallyResponse {
    /// result.
    pub result: SetParametersResult,
}

srvdef!(
    ListParametersRequest,
    LIST_REQ,
    "rcl_interfaces/srv/ListParameters_Request"
);
srvdef!(
    ListParametersResponse,
    LIST_RESP,
    "rcl_interfaces/srv/ListParameters_Response"
);
srvdef!(
    GetParametersRequest,
    GET_REQ,
    "rcl_interfaces/srv/GetParameters_Request"
);
srvdef!(
    GetParametersResponse,
    GET_RESP,
    "rcl_interfaces/srv/GetParameters_Response"
);
srvdef!(
    GetParameterTypesRequest,
    TYPES_REQ,
    "rcl_interfaces/srv/GetParameterTypes_Request"
);
srvdef!(
    GetParameterTypesResponse,
    TYPES_RESP,
    "rcl_interfaces/srv/GetParameterTypes_Response"
);
srvdef!(
    DescribeParametersRequest,
    DESC_REQ,
    "rcl_interfaces/srv/DescribeParameters_Request"
);
srvdef!(
    DescribeParametersResponse,
    DESC_RESP,
    "rcl_interfaces/srv/DescribeParameters_Response"
);
srvdef!(
    SetParametersRequest,
    SET_REQ,
    "rcl_interfaces/srv/SetParameters_Request"
);
srvdef!(
    SetParametersResponse,
    SET_RESP,
    "rcl_interfaces/srv/SetParameters_Response"
);
srvdef!(
    SetParametersAtomicallyRequest,
    SETA_REQ,
    "rcl_interfaces/srv/SetParametersAtomically_Request"
);
srvdef!(
    SetParametersAtomicallyResponse,
    SETA_RESP,
    "rcl_interfaces/srv/SetParametersAtomically_Response"
);

/// Why a parameter cannot be set.
pub const NOT_SETTABLE: &str = "rollbase has no ROS parameters: its settings are the platform file (--config) and the command-line options (--ros2-*), fixed for a run; restart it with the new values";

/// The parameter services: (service name, request DDS type, reply DDS type).
pub const SERVICES: [(&str, &MsgDef, &MsgDef); 6] = [
    ("list_parameters", &LIST_REQ, &LIST_RESP),
    ("get_parameters", &GET_REQ, &GET_RESP),
    ("get_parameter_types", &TYPES_REQ, &TYPES_RESP),
    ("describe_parameters", &DESC_REQ, &DESC_RESP),
    ("set_parameters", &SET_REQ, &SET_RESP),
    ("set_parameters_atomically", &SETA_REQ, &SETA_RESP),
];

/// `~/list_parameters`: none.
pub fn answer_list(_: &ListParametersRequest) -> ListParametersResponse {
    ListParametersResponse::default()
}

/// `~/get_parameters`: every name not set.
pub fn answer_get(r: &GetParametersRequest) -> GetParametersResponse {
    GetParametersResponse {
        values: r
            .0
            .names
            .iter()
            .map(|_| ParameterValue::default())
            .collect(),
    }
}

/// `~/get_parameter_types`: every name not set (type 0).
pub fn answer_types(r: &GetParameterTypesRequest) -> GetParameterTypesResponse {
    GetParameterTypesResponse {
        types: vec![0; r.0.names.len()],
    }
}

/// `~/describe_parameters`: a descriptor of type 0 per name, read only.
pub fn answer_describe(r: &DescribeParametersRequest) -> DescribeParametersResponse {
    DescribeParametersResponse {
        descriptors: r
            .0
            .names
            .iter()
            .map(|n| ParameterDescriptor {
                name: n.clone(),
                read_only: true,
                description: NOT_SETTABLE.into(),
                ..Default::default()
            })
            .collect(),
    }
}

/// `~/set_parameters`: refused, one result per parameter.
pub fn answer_set(r: &SetParametersRequest) -> SetParametersResponse {
    SetParametersResponse {
        results: r
            .parameters
            .iter()
            .map(|_| SetParametersResult {
                successful: false,
                reason: NOT_SETTABLE.into(),
            })
            .collect(),
    }
}

/// `~/set_parameters_atomically`: refused.
pub fn answer_set_atomically(
    _: &SetParametersAtomicallyRequest,
) -> SetParametersAtomicallyResponse {
    SetParametersAtomicallyResponse {
        result: SetParametersResult {
            successful: false,
            reason: NOT_SETTABLE.into(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::msg::{from_cdr_payload, to_cdr};

    /// `ros2 param set /rollbase x 1.5`'s request, as rclcpp encodes it (CDR little endian):
    /// one Parameter { name "x", value { type 3 (double), double_value 1.5 } }.
    fn set_request_bytes() -> Vec<u8> {
        let mut b = Vec::new();
        b.extend_from_slice(&1u32.to_le_bytes()); // one parameter
        b.extend_from_slice(&2u32.to_le_bytes()); // "x\0"
        b.extend_from_slice(b"x\0");
        b.push(3); // type: PARAMETER_DOUBLE
        b.push(0); // bool_value
        b.extend_from_slice(&[0, 0, 0, 0]); // align 8
        b.extend_from_slice(&0i64.to_le_bytes()); // integer_value
        b.extend_from_slice(&1.5f64.to_le_bytes()); // double_value
        b.extend_from_slice(&1u32.to_le_bytes()); // "" string_value
        b.push(0);
        b.extend_from_slice(&[0, 0, 0]);
        for _ in 0..5 {
            b.extend_from_slice(&0u32.to_le_bytes()); // five empty arrays
        }
        b
    }

    #[test]
    fn a_set_request_decodes_and_is_refused_with_the_reason() {
        let bytes = set_request_bytes();
        let (r, used) = from_cdr_payload::<SetParametersRequest>(&bytes, false).unwrap();
        assert_eq!(used, bytes.len());
        assert_eq!(r.parameters.len(), 1);
        assert_eq!(r.parameters[0].name, "x");
        assert_eq!(
            (
                r.parameters[0].value.kind,
                r.parameters[0].value.double_value
            ),
            (3, 1.5)
        );
        let a = answer_set(&r);
        assert_eq!(a.results.len(), 1);
        assert!(!a.results[0].successful && a.results[0].reason.contains("platform file"));
        let back = to_cdr(&a).unwrap();
        let (again, _) = from_cdr_payload::<SetParametersResponse>(&back[4..], false).unwrap();
        assert_eq!(again, a);
    }

    #[test]
    fn nothing_is_listed_and_every_name_is_not_set() {
        assert_eq!(
            answer_list(&ListParametersRequest::default()).names.len(),
            0
        );
        let names = NamesRequest {
            names: vec!["use_sim_time".into(), "a".into()],
        };
        let g = answer_get(&GetParametersRequest(names.clone()));
        assert_eq!(g.values, vec![ParameterValue::default(); 2]);
        assert_eq!(
            answer_types(&GetParameterTypesRequest(names.clone())).types,
            vec![0, 0]
        );
        let d = answer_describe(&DescribeParametersRequest(names));
        assert_eq!(d.descriptors[1].name, "a");
        assert!(d.descriptors[1].read_only);
        assert!(
            !answer_set_atomically(&SetParametersAtomicallyRequest::default())
                .result
                .successful
        );
        assert_eq!(
            SERVICES[0].1.dds_type_name(),
            "rcl_interfaces::srv::dds_::ListParameters_Request_"
        );
    }
}
