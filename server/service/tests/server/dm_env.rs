//! The dm_env_rpc endpoint: a whole episode, the sequence states, in-band errors, and worlds
//! that end with their stream.

use std::time::{Duration, Instant};

use dm::environment_request::Payload as Rq;
use dm::environment_response::Payload as Rs;
use dm::tensor::Payload as Elements;
use esrp_server::dm_env::wire::dm_env_rpc::v1 as dm;
use esrp_server::dm_env::wire::google::rpc::Status;
use esrp_server::proto;
use tokio::sync::mpsc;
use tonic::Code;

use super::harness::{Server, create_request};

/// One dm_env_rpc connection: requests go out one at a time, each answered in order.
struct Connection {
    requests: mpsc::Sender<dm::EnvironmentRequest>,
    responses: tonic::Streaming<dm::EnvironmentResponse>,
}

impl Connection {
    async fn open(server: &Server) -> Connection {
        Self::try_open(server, None).await.expect("the stream opens")
    }

    async fn try_open(server: &Server, token: Option<&str>) -> Result<Connection, tonic::Status> {
        let mut client = dm::environment_client::EnvironmentClient::connect(server.address.clone())
            .await
            .expect("the client connects")
            .max_decoding_message_size(256 << 20);
        let (requests, receiver) = mpsc::channel(16);
        let mut request = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(receiver));
        if let Some(token) = token {
            request.metadata_mut().insert("authorization", format!("Bearer {token}").parse().unwrap());
        }
        let responses = client.process(request).await?.into_inner();
        Ok(Connection { requests, responses })
    }

    /// Sends `request` and returns its answer, or the in-band error.
    async fn send(&mut self, request: Rq) -> Result<Rs, Status> {
        self.requests.send(dm::EnvironmentRequest { payload: Some(request) }).await.expect("the stream is open");
        let response = self.responses.message().await.expect("no transport error").expect("a response");
        match response.payload.expect("a payload") {
            Rs::Error(status) => Err(status),
            other => Ok(other),
        }
    }

    async fn create_world(&mut self, settings: Vec<(&str, dm::Tensor)>) -> Result<String, Status> {
        let settings = settings.into_iter().map(|(k, v)| (k.to_owned(), v)).collect();
        match self.send(Rq::CreateWorld(dm::CreateWorldRequest { settings })).await? {
            Rs::CreateWorld(r) => Ok(r.world_name),
            other => panic!("expected create_world, got {other:?}"),
        }
    }

    async fn join_world(&mut self, world_name: &str) -> Result<dm::ActionObservationSpecs, Status> {
        let request = dm::JoinWorldRequest { world_name: world_name.to_owned(), settings: Default::default() };
        match self.send(Rq::JoinWorld(request)).await? {
            Rs::JoinWorld(r) => Ok(r.specs.expect("specs")),
            other => panic!("expected join_world, got {other:?}"),
        }
    }

    async fn step(
        &mut self,
        action: Option<dm::Tensor>,
        requested_observations: &[u64],
    ) -> Result<dm::StepResponse, Status> {
        let request = dm::StepRequest {
            actions: action.into_iter().map(|a| (1, a)).collect(),
            requested_observations: requested_observations.to_vec(),
        };
        match self.send(Rq::Step(request)).await? {
            Rs::Step(r) => Ok(r),
            other => panic!("expected step, got {other:?}"),
        }
    }

    async fn destroy_world(&mut self, world_name: &str) -> Result<(), Status> {
        self.send(Rq::DestroyWorld(dm::DestroyWorldRequest { world_name: world_name.to_owned() })).await.map(drop)
    }
}

fn string(value: &str) -> dm::Tensor {
    dm::Tensor {
        shape: vec![],
        payload: Some(Elements::Strings(dm::tensor::StringArray { array: vec![value.to_owned()] })),
    }
}

fn int64(value: i64) -> dm::Tensor {
    dm::Tensor { shape: vec![], payload: Some(Elements::Int64s(dm::tensor::Int64Array { array: vec![value] })) }
}

fn action(code: i32) -> dm::Tensor {
    dm::Tensor { shape: vec![], payload: Some(Elements::Int32s(dm::tensor::Int32Array { array: vec![code] })) }
}

fn state(response: &dm::StepResponse) -> dm::EnvironmentStateType {
    dm::EnvironmentStateType::try_from(response.state).expect("a known state")
}

fn double(response: &dm::StepResponse, uid: u64) -> f64 {
    match &response.observations[&uid].payload {
        Some(Elements::Doubles(d)) => d.array[0],
        other => panic!("expected a double, got {other:?}"),
    }
}

fn check_code(result: Result<impl std::fmt::Debug, Status>, code: Code, needle: &str) {
    let status = result.expect_err("an in-band error");
    assert_eq!(status.code, code as i32, "{}", status.message);
    assert!(status.message.contains(needle), "{:?} does not mention {needle:?}", status.message);
}

/// The expert actions of `scene_id`, from a privileged esrp.v1 episode's scene JSON.
async fn expert_actions(server: &Server, scene_id: &str) -> Vec<i32> {
    let mut client = server.client().await;
    let created = client.create_episode(create_request(scene_id, true)).await.unwrap().into_inner();
    let state = client
        .get_privileged_state(proto::GetPrivilegedStateRequest { episode_id: created.episode_id.clone() })
        .await
        .unwrap()
        .into_inner();
    client.close_episode(proto::CloseEpisodeRequest { episode_id: created.episode_id }).await.unwrap();
    let scene = esrp_core::Scene::from_json(&state.scene_json).unwrap();
    scene.expert_trajectory.iter().map(|a| i32::from(a.code())).collect()
}

#[tokio::test]
async fn the_expert_succeeds_through_dm_env_rpc() {
    let server = Server::start(&[]);
    let expert = expert_actions(&server, "esrp-bench-v2/00003").await;
    let mut connection = Connection::open(&server).await;
    let world = connection.create_world(vec![("scene", string("esrp-bench-v2/00003"))]).await.unwrap();
    let specs = connection.join_world(&world).await.unwrap();

    let names: Vec<(u64, String, Vec<i32>, i32)> = {
        let mut v: Vec<_> =
            specs.observations.iter().map(|(&u, s)| (u, s.name.clone(), s.shape.clone(), s.dtype)).collect();
        v.sort();
        v
    };
    let uint8 = dm::DataType::Uint8 as i32;
    let expected = vec![
        (1, "ego_rgb".to_owned(), vec![128, 128, 3], uint8),
        (2, "goal_rgb".to_owned(), vec![128, 128, 3], uint8),
        (3, "grasping".to_owned(), vec![], dm::DataType::Bool as i32),
        (4, "reward".to_owned(), vec![], dm::DataType::Double as i32),
        (5, "discount".to_owned(), vec![], dm::DataType::Double as i32),
    ];
    assert_eq!(names, expected);
    let action_spec = &specs.actions[&1];
    assert_eq!((action_spec.name.as_str(), action_spec.dtype), ("action", dm::DataType::Int32 as i32));

    // The first step starts the sequence: its action is ignored, the reward is 0.
    let all = [1, 2, 3, 4, 5];
    let first = connection.step(Some(action(0)), &all).await.unwrap();
    assert_eq!(state(&first), dm::EnvironmentStateType::Running);
    assert_eq!(double(&first, 4), 0.0);
    match &first.observations[&1].payload {
        Some(Elements::Uint8s(rgb)) => assert_eq!(rgb.array.len(), 128 * 128 * 3),
        other => panic!("expected uint8s, got {other:?}"),
    }

    let mut total = 0.0;
    let mut last = None;
    for (i, &code) in expert.iter().enumerate() {
        let response = connection.step(Some(action(code)), &[3, 4, 5]).await.unwrap();
        total += double(&response, 4);
        let expected = if i + 1 == expert.len() {
            dm::EnvironmentStateType::Terminated
        } else {
            dm::EnvironmentStateType::Running
        };
        assert_eq!(state(&response), expected, "step {i}");
        last = Some(response);
    }
    let last = last.unwrap();
    assert_eq!(double(&last, 5), 0.0, "the discount is 0 at termination");
    assert!(total > 10.0, "the expert's return {total} includes the success bonus");

    // After TERMINATED the next step starts a new sequence, from the start.
    let again = connection.step(Some(action(0)), &[1, 1, 3]).await.unwrap();
    assert_eq!(state(&again), dm::EnvironmentStateType::Running);
    assert_eq!(again.observations.len(), 2);
    assert_eq!(again.observations[&1], first.observations[&1], "the new sequence starts where the first did");

    assert!(matches!(connection.send(Rq::LeaveWorld(dm::LeaveWorldRequest {})).await, Ok(Rs::LeaveWorld(_))));
    connection.destroy_world(&world).await.unwrap();
}

#[tokio::test]
async fn errors_are_in_band_and_the_stream_goes_on() {
    let mut server = Server::start(&[]);
    let mut connection = Connection::open(&server).await;
    check_code(connection.step(None, &[]).await, Code::FailedPrecondition, "JoinWorld");
    check_code(connection.join_world("no-such-world").await, Code::NotFound, "no-such-world");
    check_code(connection.create_world(vec![("colour", int64(1))]).await, Code::InvalidArgument, "colour");
    check_code(connection.create_world(vec![("scene", string("nope"))]).await, Code::NotFound, "nope");
    check_code(connection.create_world(vec![("resolution", int64(7))]).await, Code::InvalidArgument, "resolution");
    check_code(connection.create_world(vec![("seed", int64(-1))]).await, Code::InvalidArgument, "seed");
    check_code(connection.create_world(vec![("split", string("validation"))]).await, Code::InvalidArgument, "split");
    check_code(connection.destroy_world("no-such-world").await, Code::NotFound, "no-such-world");
    let extension = Rq::Extension(Default::default());
    check_code(connection.send(extension).await, Code::Unimplemented, "extension");

    // A horizon of 2: RUNNING (start), RUNNING, INTERRUPTED (truncated, discount 1).
    let world = connection.create_world(vec![("horizon", int64(2)), ("split", string("train"))]).await.unwrap();
    connection.join_world(&world).await.unwrap();
    check_code(connection.join_world(&world).await, Code::FailedPrecondition, "already joined");
    check_code(connection.destroy_world(&world).await, Code::FailedPrecondition, "LeaveWorld");
    assert_eq!(state(&connection.step(None, &[]).await.unwrap()), dm::EnvironmentStateType::Running);
    check_code(connection.step(None, &[]).await, Code::InvalidArgument, "required");
    check_code(connection.step(Some(action(9)), &[]).await, Code::InvalidArgument, "out of range");
    check_code(connection.step(Some(action(2)), &[0]).await, Code::InvalidArgument, "uid 0");
    let float =
        dm::Tensor { shape: vec![], payload: Some(Elements::Doubles(dm::tensor::DoubleArray { array: vec![2.0] })) };
    check_code(connection.step(Some(float), &[]).await, Code::InvalidArgument, "INT32");
    let vector = dm::Tensor { shape: vec![1], ..action(2) };
    check_code(connection.step(Some(vector), &[]).await, Code::InvalidArgument, "scalar");
    assert_eq!(state(&connection.step(Some(action(2)), &[]).await.unwrap()), dm::EnvironmentStateType::Running);
    let truncated = connection.step(Some(action(2)), &[5]).await.unwrap();
    assert_eq!(state(&truncated), dm::EnvironmentStateType::Interrupted);
    assert_eq!(double(&truncated, 5), 1.0);
    assert_eq!(state(&connection.step(None, &[]).await.unwrap()), dm::EnvironmentStateType::Running);

    // Reset ends the sequence; the next step starts another.
    match connection.send(Rq::Reset(dm::ResetRequest::default())).await {
        Ok(Rs::Reset(r)) => assert_eq!(r.specs.unwrap().observations.len(), 5),
        other => panic!("expected reset, got {other:?}"),
    }
    assert_eq!(state(&connection.step(Some(action(42)), &[]).await.unwrap()), dm::EnvironmentStateType::Running);

    // A second connection cannot join a world that has its agent.
    let mut other = Connection::open(&server).await;
    check_code(other.join_world(&world).await, Code::FailedPrecondition, "agent");

    assert!(connection.send(Rq::LeaveWorld(dm::LeaveWorldRequest {})).await.is_ok());
    assert!(connection.send(Rq::LeaveWorld(dm::LeaveWorldRequest {})).await.is_ok(), "leaving twice is a no-op");
    connection.destroy_world(&world).await.unwrap();
    check_code(connection.destroy_world(&world).await, Code::NotFound, "esrp-world-");
    assert!(server.is_running());
}

/// Long client-given names are echoed bounded in the in-band errors.
#[tokio::test]
async fn long_client_values_are_echoed_bounded() {
    let mut server = Server::start(&[]);
    let mut connection = Connection::open(&server).await;
    let long = "w".repeat(20_000);
    let short = |result: Result<String, Status>, code: Code| {
        let status = result.expect_err("the request fails");
        assert_eq!(status.code, code as i32, "{status:?}");
        assert!(status.message.len() < 512, "a message of {} bytes", status.message.len());
        assert!(status.message.contains("(20000 characters)"), "{}", status.message);
    };
    short(connection.join_world(&long).await.map(|_| String::new()), Code::NotFound);
    short(connection.destroy_world(&long).await.map(|_| String::new()), Code::NotFound);
    short(connection.create_world(vec![(long.as_str(), int64(1))]).await, Code::InvalidArgument);
    short(connection.create_world(vec![("scene", string(&long))]).await, Code::NotFound);
    short(connection.create_world(vec![("split", string(&long))]).await, Code::InvalidArgument);
    let join = dm::JoinWorldRequest { world_name: "w".into(), settings: [(long.clone(), int64(1))].into() };
    let joined = connection.send(Rq::JoinWorld(join)).await;
    short(joined.map(|_| String::new()), Code::InvalidArgument);
    let extension =
        esrp_server::dm_env::wire::google::protobuf::Any { type_url: long.clone(), value: Default::default() };
    short(connection.send(Rq::Extension(extension)).await.map(|_| String::new()), Code::Unimplemented);
    assert!(server.is_running());
}

#[tokio::test]
async fn worlds_end_with_their_stream() {
    let server = Server::start(&["--token", "sesame"]);
    assert_eq!(Connection::try_open(&server, None).await.err().map(|s| s.code()), Some(Code::Unauthenticated));
    let mut connection = Connection::try_open(&server, Some("sesame")).await.unwrap();
    for _ in 0..2 {
        connection.create_world(vec![("resolution", int64(32))]).await.unwrap();
    }
    let mut client = server.client().await;
    let live = |client: &mut esrp_server::proto::esrp_client::EsrpClient<tonic::transport::Channel>| {
        let mut request = tonic::Request::new(proto::ServerInfoRequest {});
        request.metadata_mut().insert("authorization", "Bearer sesame".parse().unwrap());
        let mut client = client.clone();
        async move { client.server_info(request).await.unwrap().into_inner().live_episodes }
    };
    assert_eq!(live(&mut client).await, 2);
    drop(connection);
    let deadline = Instant::now() + Duration::from_secs(10);
    while live(&mut client).await != 0 {
        assert!(Instant::now() < deadline, "the worlds of a closed stream are destroyed");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A world's episode is its connection's: an agent that thinks longer than the idle timeout
/// between steps finds its world as it left it (the episodes of unary creates are reaped).
#[tokio::test]
async fn a_world_outlives_the_idle_timeout_while_its_connection_is_open() {
    let server = Server::start(&["--idle-timeout-seconds", "1"]);
    let mut connection = Connection::open(&server).await;
    let world = connection.create_world(vec![("resolution", int64(32))]).await.unwrap();
    connection.join_world(&world).await.unwrap();
    connection.step(None, &[1]).await.unwrap();
    let mut client = server.client().await;
    let unary =
        client.create_episode(create_request("esrp-bench-v2/00007", false)).await.unwrap().into_inner().episode_id;
    tokio::time::sleep(Duration::from_millis(3_500)).await; // the reaper runs at least once a second
    let reaped = client.get_metrics(proto::GetMetricsRequest { episode_id: unary }).await;
    assert_eq!(reaped.err().map(|s| s.code()), Some(Code::NotFound), "an idle unary episode is reaped");
    let stepped = connection.step(Some(action(2)), &[1]).await.unwrap();
    assert_eq!(state(&stepped), dm::EnvironmentStateType::Running);
}

#[tokio::test]
async fn reset_world_interrupts_the_agent_of_another_connection() {
    let server = Server::start(&[]);
    let mut host = Connection::open(&server).await;
    let mut agent = Connection::open(&server).await;
    let world =
        host.create_world(vec![("resolution", int64(32)), ("scene", string("esrp-bench-v2/00003"))]).await.unwrap();
    agent.join_world(&world).await.unwrap();
    let start = agent.step(None, &[1]).await.unwrap();
    assert_eq!(state(&agent.step(Some(action(2)), &[]).await.unwrap()), dm::EnvironmentStateType::Running);

    // The host moves the world to another scene: the agent is told once, then starts over there.
    let settings = [("scene".to_owned(), string("esrp-bench-v2/00000"))].into();
    let reset = dm::ResetWorldRequest { world_name: world.clone(), settings };
    assert!(matches!(host.send(Rq::ResetWorld(reset)).await, Ok(Rs::ResetWorld(_))));
    let bad = dm::ResetWorldRequest { world_name: world.clone(), settings: [("horizon".to_owned(), int64(3))].into() };
    check_code(host.send(Rq::ResetWorld(bad)).await, Code::InvalidArgument, "horizon");
    let interrupted = agent.step(Some(action(2)), &[1]).await.unwrap();
    assert_eq!(state(&interrupted), dm::EnvironmentStateType::Interrupted);
    let first = agent.step(Some(action(2)), &[1]).await.unwrap();
    assert_eq!(state(&first), dm::EnvironmentStateType::Running);
    assert_eq!(first.observations[&1], interrupted.observations[&1]);
    assert_ne!(first.observations[&1], start.observations[&1], "another scene, another view");
    assert_eq!(state(&agent.step(Some(action(2)), &[]).await.unwrap()), dm::EnvironmentStateType::Running);
}

/// A world whose creating connection ends under its agent (another connection) is gone: the
/// agent's Step and Reset say so, naming the world, and after LeaveWorld it joins another.
#[tokio::test]
async fn the_agent_of_a_world_whose_creator_ended_is_told_so() {
    let server = Server::start(&[]);
    let mut host = Connection::open(&server).await;
    let mut agent = Connection::open(&server).await;
    let world = host.create_world(vec![("resolution", int64(32))]).await.unwrap();
    agent.join_world(&world).await.unwrap();
    agent.step(None, &[]).await.unwrap();
    drop(host);
    let deadline = Instant::now() + Duration::from_secs(10);
    let status = loop {
        match agent.step(Some(action(2)), &[]).await {
            Ok(_) => assert!(Instant::now() < deadline, "the world of an ended connection is destroyed"),
            Err(status) => break status,
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(status.code, Code::NotFound as i32, "{status:?}");
    assert!(status.message.contains(&world) && status.message.contains("LeaveWorld"), "{status:?}");
    check_code(agent.send(Rq::Reset(dm::ResetRequest::default())).await, Code::NotFound, "LeaveWorld");
    assert!(agent.send(Rq::LeaveWorld(dm::LeaveWorldRequest {})).await.is_ok());
    let other = agent.create_world(vec![("resolution", int64(32))]).await.unwrap();
    agent.join_world(&other).await.unwrap();
    assert_eq!(state(&agent.step(None, &[]).await.unwrap()), dm::EnvironmentStateType::Running);
}

/// A step that the agent sends while another connection's ResetWorld is under way is taken
/// either before the reset (in the old sequence) or after it (answered INTERRUPTED), never in
/// the new sequence behind the agent's back: every sequence that follows runs its whole
/// horizon from the first observation it was shown.
#[tokio::test]
async fn a_step_racing_a_reset_world_never_lands_in_the_new_sequence() {
    const HORIZON: usize = 2;
    let server = Server::start(&[]);
    let mut host = Connection::open(&server).await;
    let mut agent = Connection::open(&server).await;
    let settings = vec![("resolution", int64(256)), ("horizon", int64(HORIZON as i64)), ("split", string("train"))];
    let world = host.create_world(settings).await.unwrap();
    agent.join_world(&world).await.unwrap();
    for round in 0..6 {
        assert_eq!(state(&agent.step(None, &[]).await.unwrap()), dm::EnvironmentStateType::Running, "{round}");
        // Another scene each round: a reset that takes a while.
        let scene = string(&format!("esrp-bench-v2/{:05}", 10 + round));
        let reset = dm::ResetWorldRequest { world_name: world.clone(), settings: [("scene".to_owned(), scene)].into() };
        let (reset, raced) = tokio::join!(host.send(Rq::ResetWorld(reset)), async {
            tokio::time::sleep(Duration::from_millis(3)).await;
            agent.step(Some(action(2)), &[]).await
        });
        assert!(matches!(reset, Ok(Rs::ResetWorld(_))), "{round}: {reset:?}");
        // The reset reaches the agent (once) as an INTERRUPTED step, then a new sequence starts.
        let mut last = state(&raced.unwrap());
        while last != dm::EnvironmentStateType::Interrupted {
            last = state(&agent.step(Some(action(2)), &[]).await.unwrap());
        }
        assert_eq!(state(&agent.step(Some(action(2)), &[]).await.unwrap()), dm::EnvironmentStateType::Running);
        for step in 1..=HORIZON {
            let expected =
                if step == HORIZON { dm::EnvironmentStateType::Interrupted } else { dm::EnvironmentStateType::Running };
            let got = state(&agent.step(Some(action(2)), &[]).await.unwrap());
            assert_eq!(got, expected, "round {round}: step {step} of a sequence whose horizon is {HORIZON}");
        }
    }
}
