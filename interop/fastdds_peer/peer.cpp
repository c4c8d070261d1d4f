// A ROS 2 peer on eProsima Fast DDS (Debian's libfastrtps, the DDS under ROS 2's default rmw,
// rmw_fastrtps_cpp), written for rollbase's interop tests: it talks to rollbase's node the way
// an rclcpp node on rmw_fastrtps does, with no ROS installation.
//
// - Topics: `rt/<ns>/cmd_vel` (geometry_msgs/Twist, written), `rt/<ns>/odom`
//   (nav_msgs/Odometry, read), DDS type names `pkg::msg::dds_::Type_`, plain CDR (XCDR1), QoS as
//   rmw_qos_profile_default (reliable, volatile, keep last 10), or best effort with
//   --best-effort (what sensor-data publishers and some joystick drivers use).
// - Services (std_srvs/Trigger) in rmw_fastrtps' mapping: the request payload is the request
//   alone; it is written with WriteParams whose related_sample_identity names the client's
//   reply reader (rmw_fastrtps_shared_cpp, rmw_request.cpp); a reply is the client's when its
//   related_sample_identity names that reader (or the request writer) and carries the
//   request's sequence number (rmw_response.cpp). No mapping flag is needed on the server.
//
// The messages are encoded and decoded with Fast CDR by hand, from the .msg definitions, in a
// type support of our own that moves the serialized bytes (no fastddsgen).
//
// Usage: fastdds_peer --domain D [--ns /robot1] [--node /rollbase] [--twist VX,VY,W]
//                     [--count N] [--calls stop,rearm] [--best-effort] [--timeout S]
// Prints one JSON object per line: {"event":"matched"...}, {"event":"odom",...},
// {"event":"sent",...}, {"event":"reply",...}, {"event":"done",...}; exit 0 when every step
// succeeded, 1 otherwise (with {"event":"error","what":...}).

#include <fastcdr/Cdr.h>
#include <fastcdr/FastBuffer.h>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include <fastdds/dds/topic/TopicDataType.hpp>
#include <fastdds/rtps/common/WriteParams.h>

#include <chrono>
#include <cstdio>
#include <cstring>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

using namespace eprosima::fastdds::dds;
using eprosima::fastrtps::rtps::SerializedPayload_t;
using eprosima::fastrtps::rtps::WriteParams;

// ---- A type support that carries serialized bytes (encapsulation header included) ----------

struct Bytes {
    std::vector<uint8_t> b;
};

class RawType : public TopicDataType {
public:
    explicit RawType(const std::string& name) {
        setName(name.c_str());
        m_typeSize = 16384;
        m_isGetKeyDefined = false;
    }
    bool serialize(void* data, SerializedPayload_t* payload) override {
        auto* d = static_cast<Bytes*>(data);
        if (d->b.size() > payload->max_size) return false;
        std::memcpy(payload->data, d->b.data(), d->b.size());
        payload->length = static_cast<uint32_t>(d->b.size());
        // The representation identifier is in the first two bytes (CDR_LE: 0x0001).
        payload->encapsulation = d->b.size() > 1 && d->b[1] == 1 ? CDR_LE : CDR_BE;
        return true;
    }
    bool deserialize(SerializedPayload_t* payload, void* data) override {
        auto* d = static_cast<Bytes*>(data);
        d->b.assign(payload->data, payload->data + payload->length);
        return true;
    }
    std::function<uint32_t()> getSerializedSizeProvider(void* data) override {
        auto* d = static_cast<Bytes*>(data);
        return [d]() { return static_cast<uint32_t>(d->b.size()); };
    }
    void* createData() override { return new Bytes(); }
    void deleteData(void* data) override { delete static_cast<Bytes*>(data); }
    bool getKey(void*, eprosima::fastrtps::rtps::InstanceHandle_t*, bool) override { return false; }
};

// ---- The messages, encoded with Fast CDR from their .msg definitions -------------------------

template <typename F>
static Bytes encode(F f) {
    eprosima::fastcdr::FastBuffer buf;
    eprosima::fastcdr::Cdr cdr(buf, eprosima::fastcdr::Cdr::LITTLE_ENDIANNESS, eprosima::fastcdr::Cdr::DDS_CDR);
    cdr.serialize_encapsulation();
    f(cdr);
    Bytes out;
    out.b.assign(buf.getBuffer(), buf.getBuffer() + cdr.getSerializedDataLength());
    return out;
}

template <typename F>
static bool decode(Bytes& in, F f) {
    try {
        eprosima::fastcdr::FastBuffer buf(reinterpret_cast<char*>(in.b.data()), in.b.size());
        eprosima::fastcdr::Cdr cdr(buf, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN, eprosima::fastcdr::Cdr::DDS_CDR);
        cdr.read_encapsulation();
        f(cdr);
        return true;
    } catch (...) {
        return false;
    }
}

struct Odom {
    int32_t sec = 0;
    uint32_t nanosec = 0;
    std::string frame, child;
    double x = 0, y = 0, z = 0, qx = 0, qy = 0, qz = 0, qw = 0;
    double vx = 0, vy = 0, wz = 0;
};

static bool decode_odom(Bytes& in, Odom& o) {
    return decode(in, [&](eprosima::fastcdr::Cdr& c) {
        double cov[36], ignored;
        c >> o.sec >> o.nanosec >> o.frame >> o.child;
        c >> o.x >> o.y >> o.z >> o.qx >> o.qy >> o.qz >> o.qw;
        c.deserializeArray(cov, 36);
        c >> o.vx >> o.vy >> ignored >> ignored >> ignored >> o.wz;
        c.deserializeArray(cov, 36);
    });
}

static std::string json_str(const std::string& s) {
    std::string o = "\"";
    for (char ch : s) {
        if (ch == '"' || ch == '\\') { o += '\\'; o += ch; }
        else if (static_cast<unsigned char>(ch) < 0x20) { char b[8]; std::snprintf(b, sizeof b, "\\u%04x", ch); o += b; }
        else o += ch;
    }
    return o + "\"";
}

static void emit(const std::string& s) {
    std::printf("%s\n", s.c_str());
    std::fflush(stdout);
}

// ---- The program --------------------------------------------------------------------------

struct Args {
    int domain = 0;
    std::string ns = "";
    std::string node = "/rollbase";
    double vx = 0.25, vy = 0.0, wz = 0.0;
    int count = 5;
    std::vector<std::string> calls{"stop", "rearm"};
    bool best_effort = false;
    double timeout = 20.0;
};

static Args parse(int argc, char** argv) {
    Args a;
    for (int i = 1; i + 1 < argc || (i < argc && std::string(argv[i]) == "--best-effort"); ++i) {
        std::string k = argv[i];
        if (k == "--best-effort") { a.best_effort = true; continue; }
        std::string v = argv[++i];
        if (k == "--domain") a.domain = std::stoi(v);
        else if (k == "--ns") a.ns = v == "/" ? "" : v;
        else if (k == "--node") a.node = v;
        else if (k == "--count") a.count = std::stoi(v);
        else if (k == "--timeout") a.timeout = std::stod(v);
        else if (k == "--twist") { std::sscanf(v.c_str(), "%lf,%lf,%lf", &a.vx, &a.vy, &a.wz); }
        else if (k == "--calls") {
            a.calls.clear();
            std::stringstream ss(v);
            std::string c;
            while (std::getline(ss, c, ',')) if (!c.empty()) a.calls.push_back(c);
        }
    }
    return a;
}

static std::string guid_hex(const eprosima::fastrtps::rtps::GUID_t& g) {
    std::string s;
    char b[4];
    for (auto x : g.guidPrefix.value) { std::snprintf(b, sizeof b, "%02x", x); s += b; }
    for (auto x : g.entityId.value) { std::snprintf(b, sizeof b, "%02x", x); s += b; }
    return s;
}

int main(int argc, char** argv) {
    Args a = parse(argc, argv);
    using clock = std::chrono::steady_clock;
    auto t_start = clock::now();
    auto elapsed = [&] { return std::chrono::duration<double>(clock::now() - t_start).count(); };
    auto fail = [&](const std::string& what) {
        emit("{\"event\":\"error\",\"what\":" + json_str(what) + ",\"t\":" + std::to_string(elapsed()) + "}");
        return 1;
    };

    DomainParticipantQos pq = PARTICIPANT_QOS_DEFAULT;
    pq.name("rollbase_fastdds_peer");
    DomainParticipant* dp = DomainParticipantFactory::get_instance()->create_participant(a.domain, pq);
    if (!dp) return fail("create_participant");
    Publisher* pub = dp->create_publisher(PUBLISHER_QOS_DEFAULT);
    Subscriber* sub = dp->create_subscriber(SUBSCRIBER_QOS_DEFAULT);

    auto reg = [&](const std::string& name) {
        TypeSupport t(new RawType(name));
        t.register_type(dp);
        return t;
    };
    reg("geometry_msgs::msg::dds_::Twist_");
    reg("nav_msgs::msg::dds_::Odometry_");
    reg("std_srvs::srv::dds_::Trigger_Request_");
    reg("std_srvs::srv::dds_::Trigger_Response_");

    DataWriterQos wq = DATAWRITER_QOS_DEFAULT;
    wq.reliability().kind = RELIABLE_RELIABILITY_QOS;
    wq.durability().kind = VOLATILE_DURABILITY_QOS;
    wq.history().kind = KEEP_LAST_HISTORY_QOS;
    wq.history().depth = 10;
    DataReaderQos rq = DATAREADER_QOS_DEFAULT;
    rq.reliability().kind = RELIABLE_RELIABILITY_QOS;
    rq.durability().kind = VOLATILE_DURABILITY_QOS;
    rq.history().kind = KEEP_LAST_HISTORY_QOS;
    rq.history().depth = 100;

    Topic* t_vel = dp->create_topic("rt" + a.ns + "/cmd_vel", "geometry_msgs::msg::dds_::Twist_", TOPIC_QOS_DEFAULT);
    Topic* t_odom = dp->create_topic("rt" + a.ns + "/odom", "nav_msgs::msg::dds_::Odometry_", TOPIC_QOS_DEFAULT);
    DataWriterQos vq = wq;
    if (a.best_effort) vq.reliability().kind = BEST_EFFORT_RELIABILITY_QOS;
    DataWriter* w_vel = pub->create_datawriter(t_vel, vq);
    DataReader* r_odom = sub->create_datareader(t_odom, rq);
    if (!w_vel || !r_odom) return fail("create endpoints");

    struct Client {
        std::string name;
        DataWriter* req;
        DataReader* rep;
    };
    std::vector<Client> clients;
    for (const std::string srv : {"stop", "rearm"}) {
        std::string fq = a.node + "/" + srv;
        Topic* tq = dp->create_topic("rq" + fq + "Request", "std_srvs::srv::dds_::Trigger_Request_", TOPIC_QOS_DEFAULT);
        Topic* tr = dp->create_topic("rr" + fq + "Reply", "std_srvs::srv::dds_::Trigger_Response_", TOPIC_QOS_DEFAULT);
        Client c{srv, pub->create_datawriter(tq, wq), sub->create_datareader(tr, rq)};
        if (!c.req || !c.rep) return fail("create service endpoints " + srv);
        clients.push_back(c);
    }

    // Discovery: every endpoint matched.
    auto matched = [&]() {
        PublicationMatchedStatus ps;
        SubscriptionMatchedStatus ss;
        w_vel->get_publication_matched_status(ps);
        if (ps.current_count == 0) return false;
        r_odom->get_subscription_matched_status(ss);
        if (ss.current_count == 0) return false;
        for (auto& c : clients) {
            c.req->get_publication_matched_status(ps);
            c.rep->get_subscription_matched_status(ss);
            if (ps.current_count == 0 || ss.current_count == 0) return false;
        }
        return true;
    };
    while (!matched()) {
        if (elapsed() > a.timeout) return fail("discovery: not every endpoint matched");
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    emit("{\"event\":\"matched\",\"t\":" + std::to_string(elapsed()) + "}");

    // Odometry from the node.
    Odom o;
    bool got = false;
    while (!got) {
        if (elapsed() > a.timeout) return fail("no odometry");
        Bytes b;
        SampleInfo info;
        while (r_odom->take_next_sample(&b, &info) == ReturnCode_t::RETCODE_OK) {
            if (info.valid_data && decode_odom(b, o)) got = true;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    std::ostringstream os;
    os.precision(17);
    os << "{\"event\":\"odom\",\"frame\":" << json_str(o.frame) << ",\"child\":" << json_str(o.child)
       << ",\"x\":" << o.x << ",\"y\":" << o.y << ",\"qz\":" << o.qz << ",\"qw\":" << o.qw
       << ",\"vx\":" << o.vx << ",\"vy\":" << o.vy << ",\"wz\":" << o.wz << ",\"sec\":" << o.sec << "}";
    emit(os.str());

    // Velocity commands.
    for (int k = 0; k < a.count; ++k) {
        Bytes tw = encode([&](eprosima::fastcdr::Cdr& c) {
            double z = 0.0;
            c << a.vx << a.vy << z << z << z << a.wz;
        });
        if (!w_vel->write(&tw)) return fail("write cmd_vel");
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    emit("{\"event\":\"sent\",\"count\":" + std::to_string(a.count) + "}");

    // Service calls, as rmw_fastrtps makes them.
    int answered = 0;
    for (const auto& call : a.calls) {
        Client* c = nullptr;
        for (auto& x : clients) if (x.name == call) c = &x;
        if (!c) return fail("unknown service " + call);
        Bytes req = encode([](eprosima::fastcdr::Cdr& cdr) { uint8_t placeholder = 0; cdr << placeholder; });
        WriteParams wp;
        wp.related_sample_identity().writer_guid(c->rep->guid());
        auto t_call = clock::now();
        if (!c->req->write(&req, wp)) return fail("write request " + call);
        auto sid = wp.sample_identity();
        bool replied = false;
        while (!replied) {
            if (std::chrono::duration<double>(clock::now() - t_call).count() > a.timeout)
                return fail("no reply from " + a.node + "/" + call);
            Bytes rep;
            SampleInfo info;
            while (c->rep->take_next_sample(&rep, &info) == ReturnCode_t::RETCODE_OK) {
                if (!info.valid_data) continue;
                const auto& rel = info.related_sample_identity;
                bool mine = (rel.writer_guid() == c->rep->guid() || rel.writer_guid() == c->req->guid()) &&
                            rel.sequence_number() == sid.sequence_number();
                if (!mine) continue;
                bool success = false;
                std::string message;
                if (!decode(rep, [&](eprosima::fastcdr::Cdr& cdr) { cdr >> success >> message; }))
                    return fail("undecodable reply from " + call);
                double ms = std::chrono::duration<double, std::milli>(clock::now() - t_call).count();
                emit("{\"event\":\"reply\",\"service\":" + json_str(call) + ",\"success\":" +
                     (success ? "true" : "false") + ",\"message\":" + json_str(message) +
                     ",\"ms\":" + std::to_string(ms) + ",\"reader\":" + json_str(guid_hex(c->rep->guid())) + "}");
                replied = true;
                ++answered;
            }
            std::this_thread::sleep_for(std::chrono::milliseconds(2));
        }
    }
    emit("{\"event\":\"done\",\"answered\":" + std::to_string(answered) + ",\"t\":" + std::to_string(elapsed()) + "}");
    dp->delete_contained_entities();
    DomainParticipantFactory::get_instance()->delete_participant(dp);
    return 0;
}
